# Run at every build (cmake -P): writes build_info.cpp with the sources' git revision. The file is
# rewritten only when its text changes, so an unchanged revision recompiles nothing.
#   -DSOURCE=<source tree> -DOUT=<build_info.cpp> -DGIT=<git or empty>
#   -DBEAMPACK_VERSION=<x.y.z> -DBEAMPACK_BUILD_TYPE=<type>
set(BEAMPACK_REVISION unknown)
if(GIT)
  execute_process(COMMAND ${GIT} -C ${SOURCE} describe --always --dirty --abbrev=12
                  RESULT_VARIABLE code OUTPUT_VARIABLE described ERROR_QUIET
                  OUTPUT_STRIP_TRAILING_WHITESPACE)
  if(code EQUAL 0 AND described)
    set(BEAMPACK_REVISION ${described})
  endif()
endif()
if(NOT BEAMPACK_BUILD_TYPE)
  set(BEAMPACK_BUILD_TYPE "none")  # CMAKE_BUILD_TYPE not set: the compiler's default flags
endif()
configure_file(${SOURCE}/cmake/build_info.cpp.in ${OUT} @ONLY)
