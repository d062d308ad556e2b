# The folders tell the architecture (STYLE.md points 1-2), checked on every test run:
# - one file of the library includes Embree (engine/embree_scene.cpp), and one benchmark file
#   (bench_trace.cpp, whose baselines call Embree's built-in spheres directly);
# - dependencies point one way: geometry/ includes none of thermal/, engine/ or tools/; thermal/
#   none of engine/ or tools/; engine/ none of tools/.
# Run as cmake -DSOURCE=<repository root> -P layout_check.cmake.
cmake_minimum_required(VERSION 3.20)
file(GLOB_RECURSE sources RELATIVE ${SOURCE}
     ${SOURCE}/engine/*.[ch]* ${SOURCE}/geometry/*.[ch]* ${SOURCE}/thermal/*.[ch]*
     ${SOURCE}/tools/*.[ch]* ${SOURCE}/tests/*.[ch]* ${SOURCE}/benchmarks/*.[ch]*
     ${SOURCE}/examples/*.[ch]* ${SOURCE}/fuzz/*.[ch]*)
set(allowed_embree engine/embree_scene.cpp benchmarks/bench_trace.cpp)
set(failures "")
foreach(file IN LISTS sources)
  file(STRINGS ${SOURCE}/${file} includes REGEX "^[ \t]*#[ \t]*include")
  string(REGEX MATCH "^[a-z]+" folder ${file})
  foreach(line IN LISTS includes)
    if(line MATCHES "[<\"]embree[0-9]*/" AND NOT file IN_LIST allowed_embree)
      list(APPEND failures "${file} includes Embree (${line}): only engine/embree_scene.cpp and benchmarks/bench_trace.cpp may")
    endif()
    set(forbidden "")
    if(folder STREQUAL "geometry")
      set(forbidden "thermal|engine|tools")
    elseif(folder STREQUAL "thermal")
      set(forbidden "engine|tools")
    elseif(folder STREQUAL "engine")
      set(forbidden "tools")
    endif()
    if(forbidden AND line MATCHES "\"([a-z.]+/)*(\\.\\./)?(${forbidden})/")
      list(APPEND failures "${file} (in ${folder}/) includes a later layer: ${line}")
    endif()
  endforeach()
endforeach()
if(failures)
  list(JOIN failures "\n" text)
  message(FATAL_ERROR "${text}")
endif()
list(LENGTH sources count)
message(STATUS "layout: ${count} sources checked")
