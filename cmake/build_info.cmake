# Run at every build (cmake -P): writes build_info.cpp with the sources' git revision. The file is
# rewritten only when its text changes, so an unchanged build recompiles nothing.
#   -DSOURCE=<source tree> -DOUT=<build_info.cpp> -DGIT=<git or empty>
#   -DBEAMPACK_VERSION=<x.y.z> -DBEAMPACK_BUILD_TYPE=<type> -DBEAMPACK_FLAGS=<compiler flags>
# Only beampack's own checkout counts: sources copied into another project's repository (a vendored
# third_party/beampack, a tarball unpacked inside a repository) would otherwise take its commit.
set(BEAMPACK_REVISION unknown)  # kUnknownRevision in engine/build_info.h

# A digest of the sources' uncommitted changes: each tracked path whose content differs from
# HEAD's, with its content's hash ("deleted" for none). Empty when the files are HEAD's, a file
# touched but unchanged included; "?" when git could not tell. Nothing here refreshes git's index,
# so a build takes no .git/index.lock (a `git commit` beside it would fail on it), and contents,
# not diff text, are hashed (colour, prefixes or the diff algorithm in a user's settings would
# change the text).
function(uncommitted_digest out)
  execute_process(COMMAND ${GIT} -C ${SOURCE} -c diff.autoRefreshIndex=false -c core.quotePath=false
                          diff HEAD --name-only --no-renames
                  RESULT_VARIABLE code OUTPUT_VARIABLE paths ERROR_QUIET
                  OUTPUT_STRIP_TRAILING_WHITESPACE)
  if(NOT code EQUAL 0)
    set(${out} "?" PARENT_SCOPE)
    return()
  endif()
  string(REPLACE "\n" ";" paths "${paths}")
  set(changes "")
  foreach(path IN LISTS paths)
    execute_process(COMMAND ${GIT} -C ${SOURCE} rev-parse --verify --quiet "HEAD:${path}"
                    OUTPUT_VARIABLE committed ERROR_QUIET OUTPUT_STRIP_TRAILING_WHITESPACE)
    set(current deleted)
    if(EXISTS "${SOURCE}/${path}")
      execute_process(COMMAND ${GIT} -C ${SOURCE} hash-object -- "${path}"
                      OUTPUT_VARIABLE current ERROR_QUIET OUTPUT_STRIP_TRAILING_WHITESPACE)
    endif()
    if(NOT current STREQUAL committed)
      string(APPEND changes "${path} ${current}\n")
    endif()
  endforeach()
  set(digest "")
  if(changes)
    string(SHA1 digest "${changes}")
    string(SUBSTRING "${digest}" 0 12 digest)
  endif()
  set(${out} "${digest}" PARENT_SCOPE)
endfunction()

if(GIT AND EXISTS ${SOURCE}/.git)
  execute_process(COMMAND ${GIT} -C ${SOURCE} rev-parse --show-toplevel
                  RESULT_VARIABLE code OUTPUT_VARIABLE top ERROR_QUIET OUTPUT_STRIP_TRAILING_WHITESPACE)
  file(REAL_PATH "${SOURCE}" source_real)
  if(code EQUAL 0 AND top)
    file(REAL_PATH "${top}" top_real)
  endif()
  if(code EQUAL 0 AND top_real STREQUAL source_real)
    # describe --dirty would refresh the index: -dirty comes from uncommitted_digest, and its
    # digest tells two edits of one commit apart, so a resume after an edit and a rebuild warns.
    execute_process(COMMAND ${GIT} -C ${SOURCE} describe --always --abbrev=12
                    RESULT_VARIABLE code OUTPUT_VARIABLE described ERROR_QUIET
                    OUTPUT_STRIP_TRAILING_WHITESPACE)
    uncommitted_digest(digest)
    if(digest STREQUAL "?")
      set(code 1)  # which changes the build holds is unknown, so its revision is
    elseif(digest)
      string(APPEND described "-dirty.${digest}")
    endif()
    # A tag may hold any text: keep 80 letters, digits and ._+- (within what is_revision_text in
    # engine/build_info.h accepts), the tail where it is longer (the commit, -dirty and the digest
    # are at the end).
    string(REGEX REPLACE "[^A-Za-z0-9._+-]" "_" described "${described}")
    string(LENGTH "${described}" length)
    if(length GREATER 80)
      math(EXPR first "${length} - 80")
      string(SUBSTRING "${described}" ${first} 80 described)
    endif()
    if(code EQUAL 0 AND described)
      set(BEAMPACK_REVISION ${described})
    endif()
  endif()
  if(BEAMPACK_REVISION STREQUAL "unknown")
    message(STATUS "beampack: ${SOURCE} has a .git but git gave no revision (not this checkout's, "
                   "or refused): builds record the revision as unknown")
  endif()
endif()
if(NOT BEAMPACK_BUILD_TYPE)
  set(BEAMPACK_BUILD_TYPE "none")  # CMAKE_BUILD_TYPE not set: the compiler's default flags
endif()
string(STRIP "${BEAMPACK_FLAGS}" BEAMPACK_FLAGS)
# The flags go into a C string: its quotes and backslashes escaped.
string(REPLACE "\\" "\\\\" BEAMPACK_FLAGS "${BEAMPACK_FLAGS}")
string(REPLACE "\"" "\\\"" BEAMPACK_FLAGS "${BEAMPACK_FLAGS}")
configure_file(${SOURCE}/cmake/build_info.cpp.in ${OUT} @ONLY)
