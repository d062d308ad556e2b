#include "tools/quit_cleanup.h"

#include <unistd.h>

#include <atomic>
#include <cstring>

namespace beampack::tools {
namespace {

constexpr std::size_t kPathBytes = 4096;
constexpr char kTemporaryInfix[] = ".tmp.";  // temporary_path's, before the pid

// A temporary file's slot: free, being filled (the handler leaves it), or holding a path.
enum SlotState : int { kFree = 0, kFilling = 1, kHeld = 2 };
struct FileSlot {
  std::atomic<int> state{kFree};
  char path[kPathBytes];
};
constexpr int kFileSlots = 8;  // a run's end stages four files at once
FileSlot file_slots[kFileSlots];

// The folders: written while `folder_count` is 0 (the handler reads the first folder_count of
// them). They are set once per command, at its start; rmdir removes only empty folders.
constexpr int kMaxFolders = 64;
char folders[kMaxFolders][kPathBytes];
std::atomic<int> folder_count{0};

// Every temporary file this process writes is a temporary_path: the handler unlinks no name
// without its ending, even one read part way through a slot's reuse on another thread.
bool ends_as_temporary(const char* path) noexcept {
  char suffix[32];
  std::memcpy(suffix, kTemporaryInfix, sizeof kTemporaryInfix);
  long pid = static_cast<long>(::getpid());
  char digits[24];
  int n = 0;
  do digits[n++] = static_cast<char>('0' + pid % 10), pid /= 10;
  while (pid > 0);
  std::size_t k = sizeof kTemporaryInfix - 1;
  while (n > 0) suffix[k++] = digits[--n];
  suffix[k] = '\0';
  const std::size_t length = ::strnlen(path, kPathBytes);
  return length > k && length < kPathBytes && std::memcmp(path + length - k, suffix, k) == 0;
}

}  // namespace

std::string temporary_path(const std::string& path) {
  return path + kTemporaryInfix + std::to_string(::getpid());
}

QuitRemovesFile::QuitRemovesFile(const std::string& path) noexcept {
  if (path.size() >= kPathBytes) return;
  for (int s = 0; s < kFileSlots; ++s) {
    int expected = kFree;
    if (!file_slots[s].state.compare_exchange_strong(expected, kFilling)) continue;
    std::memcpy(file_slots[s].path, path.c_str(), path.size() + 1);
    file_slots[s].state.store(kHeld, std::memory_order_release);
    slot_ = s;
    return;
  }
}

QuitRemovesFile::~QuitRemovesFile() {
  if (slot_ >= 0) file_slots[slot_].state.store(kFree, std::memory_order_release);
}

void quit_removes_folders(const std::vector<std::filesystem::path>& made) noexcept {
  folder_count.store(0, std::memory_order_release);
  int n = 0;
  for (const std::filesystem::path& folder : made) {
    const std::string& text = folder.native();
    if (n == kMaxFolders || text.size() >= kPathBytes) break;  // the outer ones are kept
    std::memcpy(folders[n++], text.c_str(), text.size() + 1);
  }
  folder_count.store(n, std::memory_order_release);
}

void remove_on_quit() noexcept {
  for (FileSlot& slot : file_slots)
    if (slot.state.load(std::memory_order_acquire) == kHeld && ends_as_temporary(slot.path))
      ::unlink(slot.path);
  for (int k = folder_count.load(std::memory_order_acquire); k-- > 0;)
    if (::rmdir(folders[k]) != 0) return;
}

}  // namespace beampack::tools
