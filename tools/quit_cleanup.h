#pragma once
// What a second interrupt removes before it ends the process at once (run_command.cpp's
// on_interrupt): the temporary files being written and the --out folders the command made, while
// they are empty. No destructor runs then, so they are kept here in a form a signal handler can
// use (fixed storage, atomics, unlink and rmdir only).
#include <filesystem>
#include <string>
#include <vector>

namespace beampack::tools {

// The temporary an output file is written to before it is renamed into place: path.tmp.<pid>.
// The handler removes no file whose name does not end so.
std::string temporary_path(const std::string& path);

// A temporary output file, registered while it lives (from before it is opened until after it is
// renamed or removed). A name too long to keep, or beyond the slots, is not registered.
class QuitRemovesFile {
 public:
  explicit QuitRemovesFile(const std::string& path) noexcept;
  ~QuitRemovesFile();
  QuitRemovesFile(const QuitRemovesFile&) = delete;
  QuitRemovesFile& operator=(const QuitRemovesFile&) = delete;

 private:
  int slot_ = -1;
};

// The folders a command made for its output, outermost first; replaces any earlier list (an empty
// list clears it).
void quit_removes_folders(const std::vector<std::filesystem::path>& made) noexcept;

// For the signal handler only: unlinks the registered temporary files, then removes the folders
// innermost first while they are empty. Async-signal-safe.
void remove_on_quit() noexcept;

}  // namespace beampack::tools
