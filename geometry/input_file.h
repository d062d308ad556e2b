#pragma once
// Input files (run files, packing files) are looked at before they are opened.
#include <cstdio>
#include <filesystem>
#include <string>

namespace beampack {

// Whether path names something that must not be opened as an input: it exists, and is neither a
// regular file nor a pipe a shell made, whose writer is already running: process substitution's
// (`beampack run <(beampack config)`) or standard input's (`... | beampack run /dev/stdin`,
// a link to /proc/self/fd/0). A named FIFO would block the open until a writer
// came (no signal ended that), and a device such as /dev/zero would be read until memory ran
// out. A missing path is left to the open, which names it.
inline bool unsafe_input_file(const std::string& path) {
  std::error_code ec;
  const std::filesystem::file_status st = std::filesystem::status(path, ec);
  if (!std::filesystem::exists(st) || std::filesystem::is_regular_file(st)) return false;
  return !(
      std::filesystem::is_fifo(st) &&
      (path.starts_with("/dev/fd/") || path.starts_with("/proc/self/fd/") || path == "/dev/stdin"));
}

// A byte of an input as a message shows it: \xNN (a NUL, a control byte or one that is not UTF-8
// would not show, or would cut the message short).
inline std::string escaped_byte(unsigned char b) {
  char hex[8];
  std::snprintf(hex, sizeof hex, "\\x%02X", b);
  return hex;
}

}  // namespace beampack
