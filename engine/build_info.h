#pragma once
// What built this library, for the record a run keeps of itself (summary.json, beampack
// --version): results are only comparable when one knows the code that made them.

namespace beampack {

// The revision of a build made outside its git checkout (cmake/build_info.cmake writes the same
// text), and of the builds behind a format-4 checkpoint.
inline constexpr const char* kUnknownRevision = "unknown";

struct BuildInfo {
  const char* version;     // the project's (CMakeLists.txt), e.g. "0.1.0"
  const char* revision;    // `git describe --always --dirty` of the sources when built;
                           // kUnknownRevision outside a git checkout
  const char* build_type;  // CMAKE_BUILD_TYPE: "Release", "RelWithDebInfo", ...
  const char* compiler;    // e.g. "gcc 12.2.0"
  const char* flags;       // CMAKE_CXX_FLAGS and the build type's, e.g. "-O2 -g -DNDEBUG"
};

BuildInfo build_info();

}  // namespace beampack
