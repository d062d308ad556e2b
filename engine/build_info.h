#pragma once
// What built this library, for the record a run keeps of itself (summary.json, beampack
// --version): results are only comparable when one knows the code that made them.
#include <cstddef>
#include <string_view>

namespace beampack {

// The revision of a build made outside its git checkout (cmake/build_info.cmake writes the same
// text), and of the builds behind a format-4 checkpoint.
inline constexpr const char* kUnknownRevision = "unknown";

// What a checkpoint's record of a revision may hold: 1 to 200 printable ASCII characters without
// spaces; anything else is damage. cmake/build_info.cmake reduces git's text to at most 80
// letters, digits and ._+- (builds of format-5 checkpoints kept it as it came), and the
// generated build_info.cpp asserts that this build's revision passes.
inline constexpr std::size_t kMaxRevisionLength = 200;
constexpr bool is_revision_text(std::string_view s) {
  if (s.empty() || s.size() > kMaxRevisionLength) return false;
  for (const char c : s)
    if (c <= ' ' || c >= 127) return false;
  return true;
}

struct BuildInfo {
  const char* version;     // the project's (CMakeLists.txt), e.g. "0.2.0"
  const char* revision;    // the sources' `git describe --always --abbrev=12` when built, then
                           // "-dirty." and a digest of the changed files' contents where tracked
                           // files differ from it (cmake/build_info.cmake); kUnknownRevision
                           // outside beampack's own checkout
  const char* build_type;  // CMAKE_BUILD_TYPE: "Release", "RelWithDebInfo", ...
  const char* compiler;    // e.g. "gcc 12.2.0"
  const char* flags;       // CMAKE_CXX_FLAGS and the build type's, e.g. "-O2 -g -DNDEBUG"
};

BuildInfo build_info();

}  // namespace beampack
