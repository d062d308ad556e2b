#pragma once
// Input files (run files, packing files) are looked at before they are opened.
#include <filesystem>
#include <string>

namespace beampack {

// Whether path can be read as an input without blocking or reading without end: a regular file,
// or the pipe a shell makes for process substitution (`beampack run <(beampack config)`), whose
// writer is already running. A named FIFO would block the open until a writer came (no signal
// ended that), and a device such as /dev/zero would be read until memory ran out.
inline bool readable_input_file(const std::string& path) {
  std::error_code ec;
  const std::filesystem::file_status st = std::filesystem::status(path, ec);
  if (std::filesystem::is_regular_file(st)) return true;
  return std::filesystem::is_fifo(st) && (path.starts_with("/dev/fd/") || path.starts_with("/proc/self/fd/"));
}

}  // namespace beampack
