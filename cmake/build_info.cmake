# Run at every build (cmake -P): writes build_info.cpp with the sources' git revision. The file is
# rewritten only when its text changes, so an unchanged build recompiles nothing.
#   -DSOURCE=<source tree> -DOUT=<build_info.cpp> -DGIT=<git or empty>
#   -DBEAMPACK_VERSION=<x.y.z> -DBEAMPACK_BUILD_TYPE=<type> -DBEAMPACK_FLAGS=<compiler flags>
# Only beampack's own checkout counts: sources copied into another project's repository (a vendored
# third_party/beampack, a tarball unpacked inside a repository) would otherwise take its commit.
set(BEAMPACK_REVISION unknown)  # kUnknownRevision in engine/build_info.h
# git takes no optional lock (an index refresh) at each build: a `git commit` running beside a
# build would otherwise fail on .git/index.lock.
set(ENV{GIT_OPTIONAL_LOCKS} 0)
if(GIT AND EXISTS ${SOURCE}/.git)
  execute_process(COMMAND ${GIT} -C ${SOURCE} rev-parse --show-toplevel
                  RESULT_VARIABLE code OUTPUT_VARIABLE top ERROR_QUIET OUTPUT_STRIP_TRAILING_WHITESPACE)
  file(REAL_PATH "${SOURCE}" source_real)
  if(code EQUAL 0 AND top)
    file(REAL_PATH "${top}" top_real)
  endif()
  if(code EQUAL 0 AND top_real STREQUAL source_real)
    execute_process(COMMAND ${GIT} -C ${SOURCE} describe --always --dirty --abbrev=12
                    RESULT_VARIABLE code OUTPUT_VARIABLE described ERROR_QUIET
                    OUTPUT_STRIP_TRAILING_WHITESPACE)
    # -dirty names no build: a digest of the uncommitted changes (tracked files) tells two
    # edits of one commit apart, so a resume after an edit and a rebuild warns.
    if(code EQUAL 0 AND described MATCHES "-dirty$")
      execute_process(COMMAND ${GIT} -C ${SOURCE} diff HEAD --no-ext-diff --no-textconv --binary
                      OUTPUT_VARIABLE changes ERROR_QUIET)
      string(SHA1 digest "${changes}")
      string(SUBSTRING "${digest}" 0 12 digest)
      string(APPEND described ".${digest}")
    endif()
    # A tag may hold any text: keep what is_revision_text (engine/build_info.h) accepts, the
    # tail where it is too long (the commit, -dirty and the digest are at the end).
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
