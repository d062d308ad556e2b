#pragma once
// The beampack command as the command-line tests run it: its exit code and everything it printed.
#include <sys/wait.h>

#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>

namespace beampack::testing {

struct Result {
  int code;
  std::string output;  // stdout and stderr, through one pipe
};

// `beampack args`, optionally under `prefix` (e.g. "timeout -s INT 1").
inline Result run(const std::string& args, const std::string& prefix = "") {
  const std::string command = prefix + " " + std::string(BEAMPACK_CLI) + " " + args + " 2>&1";
  std::FILE* pipe = popen(command.c_str(), "r");
  std::string out;
  std::array<char, 4096> buf;
  while (std::fgets(buf.data(), buf.size(), pipe)) out += buf.data();
  const int status = pclose(pipe);
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, out};
}

// Writes `text` to `path`; returns the path, to put in a command line.
inline std::string write(const std::filesystem::path& path, const std::string& text) {
  std::ofstream(path) << text;
  return path.string();
}

inline std::string file_text(const std::filesystem::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

}  // namespace beampack::testing
