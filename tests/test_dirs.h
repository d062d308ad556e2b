#pragma once
// Where a test process writes its files: a folder of its own under the system's temporary folder
// (the process id keeps two test runs at once, two build trees or CI beside a developer, apart),
// removed when every test of the process passed and kept for a look otherwise.
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <string>

namespace beampack::testing {

// This process's folder, made on first use.
inline const std::filesystem::path& process_dir() {
  static const std::filesystem::path dir = [] {
    auto d =
        std::filesystem::temp_directory_path() / ("beampack_tests_" + std::to_string(::getpid()));
    std::filesystem::create_directories(d);
    return d;
  }();
  return dir;
}

struct RemoveProcessDirWhenPassed : ::testing::Environment {
  void TearDown() override {
    if (::testing::UnitTest::GetInstance()->Passed()) std::filesystem::remove_all(process_dir());
  }
};
inline ::testing::Environment* const remove_process_dir =
    ::testing::AddGlobalTestEnvironment(new RemoveProcessDirWhenPassed);

// An empty folder `name` in this process's folder.
inline std::filesystem::path fresh_dir(const std::string& name) {
  const std::filesystem::path dir = process_dir() / name;
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  return dir;
}

}  // namespace beampack::testing
