# Install.AProjectOfYourOwnBuildsAgainstTheInstalledLibrary (ctest runs this with cmake -P):
# installs this build into a scratch prefix, builds examples/ against it as another project does
# (find_package(beampack), #include <beampack/...>), runs the example and checks what it prints.
# With -DFROM_BUILD_TREE=ON it installs nothing and finds the package in the build tree
# (Install.AProjectOfYourOwnBuildsAgainstThisBuildTree).
#   -DSOURCE=<source tree> -DBUILD=<build tree> -DWORK=<scratch folder> -DCXX=<compiler>
#   -DGENERATOR=<the build's generator> -DMAKE_PROGRAM=<its make program>
#   -DPREFIXES=<the build's CMAKE_PREFIX_PATH, "|" between entries>
#   -DCONFIG=<the configuration tested: the build type, or a multi-config generator's>
file(REMOVE_RECURSE ${WORK})
set(config)
if(CONFIG)
  set(config --config ${CONFIG})
endif()

function(step what)
  execute_process(COMMAND ${ARGN} RESULT_VARIABLE code OUTPUT_VARIABLE out ERROR_VARIABLE out)
  if(NOT code EQUAL 0)
    message(FATAL_ERROR "${what} failed (${code}):\n${out}")
  endif()
  set(printed "${out}" PARENT_SCOPE)
endfunction()

if(FROM_BUILD_TREE)  # Install.AProjectOfYourOwnBuildsAgainstThisBuildTree: no install
  string(REPLACE "|" ";" prefixes "${BUILD}|${PREFIXES}")
else()
  step("install" ${CMAKE_COMMAND} --install ${BUILD} ${config} --prefix ${WORK}/prefix)
  if(EXISTS ${WORK}/prefix/include/engine OR EXISTS ${WORK}/prefix/include/geometry)
    message(FATAL_ERROR "headers installed outside include/beampack")
  endif()
  string(REPLACE "|" ";" prefixes "${WORK}/prefix|${PREFIXES}")
endif()
step("configuring examples/" ${CMAKE_COMMAND} -S ${SOURCE}/examples -B ${WORK}/build
     -G ${GENERATOR} -DCMAKE_MAKE_PROGRAM=${MAKE_PROGRAM} "-DCMAKE_PREFIX_PATH=${prefixes}"
     -DCMAKE_CXX_COMPILER=${CXX} -DCMAKE_BUILD_TYPE=${CONFIG})
step("building examples/" ${CMAKE_COMMAND} --build ${WORK}/build ${config})
set(example ${WORK}/build/run_in_code)
if(NOT EXISTS ${example})  # a multi-config generator's folder of the configuration
  set(example ${WORK}/build/${CONFIG}/run_in_code)
endif()
step("running the example" ${example})

# The example's five pulses (pulses.count in examples/run_in_code.cpp) of 6e-10 J each, the
# energies summed since the start: every pulse line books its absorbed energy within what was
# injected, the injected energy grows with each pulse, and the hottest particle is above the
# 300 K start.
string(REGEX MATCHALL "pulse [0-9]+: [^\n]*" pulses "${printed}")
list(LENGTH pulses count)
if(NOT count EQUAL 5)
  message(FATAL_ERROR "expected 5 pulse lines, got ${count}:\n${printed}")
endif()
set(injected_before 0)
foreach(line IN LISTS pulses)
  if(NOT line MATCHES "absorbed ([0-9.e+-]+) J of ([0-9.e+-]+) J")
    message(FATAL_ERROR "no energy in: ${line}")
  endif()
  if(NOT CMAKE_MATCH_1 GREATER 0 OR CMAKE_MATCH_1 GREATER CMAKE_MATCH_2)
    message(FATAL_ERROR "absorbed outside (0, injected]: ${line}")
  endif()
  if(NOT CMAKE_MATCH_2 GREATER injected_before)
    message(FATAL_ERROR "injected energy not grown since the pulse before: ${line}")
  endif()
  set(injected_before ${CMAKE_MATCH_2})
endforeach()
if(NOT printed MATCHES "hottest particle: ([0-9.]+) K" OR NOT CMAKE_MATCH_1 GREATER 300)
  message(FATAL_ERROR "no heating seen:\n${printed}")
endif()
file(REMOVE_RECURSE ${WORK})
