# Run at every build (cmake -P): writes build_info.cpp with the sources' git revision. The file is
# rewritten only when its text changes, so an unchanged revision recompiles nothing.
#   -DSOURCE=<source tree> -DOUT=<build_info.cpp> -DGIT=<git or empty>
#   -DBEAMPACK_VERSION=<x.y.z> -DBEAMPACK_BUILD_TYPE=<type> -DBEAMPACK_FLAGS=<compiler flags>
# Only beampack's own checkout counts: sources copied into another project's repository (a vendored
# third_party/beampack, a tarball unpacked inside a repository) would otherwise take its commit.
set(BEAMPACK_REVISION unknown)  # kUnknownRevision in engine/build_info.h
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
    # A tag may hold any text: keep what a checkpoint's record accepts (short, plain ASCII).
    string(REGEX REPLACE "[^A-Za-z0-9._+-]" "_" described "${described}")
    string(SUBSTRING "${described}" 0 80 described)
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
# The flags go into a C string: its quotes and backslashes escaped.
string(REPLACE "\\" "\\\\" BEAMPACK_FLAGS "${BEAMPACK_FLAGS}")
string(REPLACE "\"" "\\\"" BEAMPACK_FLAGS "${BEAMPACK_FLAGS}")
configure_file(${SOURCE}/cmake/build_info.cpp.in ${OUT} @ONLY)
