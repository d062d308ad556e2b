// Replays every seed and regression input of the fuzz targets (fuzz/corpus/<target>/,
// fuzz/regressions/<target>/) through the same checks the fuzzers run, so the default test run
// keeps them fixed without clang or libFuzzer. Then the specific findings, each with the outcome
// a user must see.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "fuzz/fuzz_checks.h"
#include "tests/expect_error.h"

namespace beampack::fuzz {
namespace {

namespace fs = std::filesystem;

std::vector<std::uint8_t> bytes_of(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

// Every file under fuzz/<kind>/<target>/; at least one must exist.
template <class Check>
void replay(const std::string& target, Check check) {
  std::size_t files = 0;
  for (const char* kind : {"corpus", "regressions"}) {
    const fs::path dir = fs::path(BEAMPACK_FUZZ_DIR) / kind / target;
    if (!fs::exists(dir)) continue;
    for (const auto& entry : fs::directory_iterator(dir)) {
      if (!entry.is_regular_file()) continue;
      ++files;
      const Outcome o = check(bytes_of(entry.path()));
      EXPECT_EQ(o.bug, "") << entry.path();
      EXPECT_TRUE(o.accepted || !o.input_error.empty()) << entry.path();
    }
  }
  EXPECT_GT(files, 0u) << "no inputs for " << target;
}

TEST(FuzzRegressions, RunFileInputsAreAcceptedOrRefusedCleanly) {
  replay("run_config", [](const std::vector<std::uint8_t>& b) { return check_run_file(b); });
}

TEST(FuzzRegressions, PackingFileInputsAreAcceptedOrRefusedCleanly) {
  replay("packing_file", [](const std::vector<std::uint8_t>& b) { return check_packing_file(b); });
}

// The seeds mean what they say: a preset's file is accepted, a misspelled key is refused.
TEST(FuzzRegressions, SeedOutcomes) {
  const fs::path corpus = fs::path(BEAMPACK_FUZZ_DIR) / "corpus";
  EXPECT_TRUE(check_run_file(bytes_of(corpus / "run_config" / "zohdi2013.toml")).accepted);
  const Outcome typo = check_run_file(bytes_of(corpus / "run_config" / "misspelled_key.toml"));
  EXPECT_CONTAINS(typo.input_error, "did you mean `material.conductivity`");
  EXPECT_TRUE(check_packing_file(bytes_of(corpus / "packing_file" / "csv_crlf.txt")).accepted);
  EXPECT_CONTAINS(
      check_packing_file(bytes_of(corpus / "packing_file" / "nan_radius.txt")).input_error,
      "not finite");
}

// What fuzz/ found, as the user sees it now: a clean error naming the line, never a crash.
TEST(FuzzRegressions, FindingsAreInputErrorsNamingTheLine) {
  const fs::path found = fs::path(BEAMPACK_FUZZ_DIR) / "regressions" / "run_config";
  // A quoted key with a dot was looked up as a path (null dereference); "" as a key indexed an
  // empty vector.
  const Outcome dotted = check_run_file(bytes_of(found / "quoted_key_with_dot.toml"));
  EXPECT_CONTAINS(dotted.input_error, ":1: key \"a.b\"");
  const Outcome empty = check_run_file(bytes_of(found / "empty_quoted_key.toml"));
  EXPECT_CONTAINS(empty.input_error, ":1: key \"\"");
  // A non-ASCII character between tokens sent toml++ 3.3.0 into __builtin_unreachable.
  const Outcome between = check_run_file(bytes_of(found / "toml_non_ascii_between_tokens.toml"));
  EXPECT_CONTAINS(between.input_error, ":2: unexpected character \\xC3\\xBD outside a string");
  // A non-ASCII character right after a bare value (`0"""è"`: no string to toml++) reached the
  // same __builtin_unreachable, from a file and from --set (the fuzzer's input).
  const Outcome after_value = check_run_file(bytes_of(found / "non_ascii_after_bare_value.toml"));
  EXPECT_CONTAINS(after_value.input_error, "run.toml:1:");
  EXPECT_FALSE(check_run_file(bytes_of(found / "non_ascii_after_bare_value_in_set.toml")).accepted);
  // Invalid UTF-8 is refused before parsing, naming the line.
  const Outcome bad_utf8 = check_run_file(bytes_of(found / "invalid_utf8_in_string.toml"));
  EXPECT_CONTAINS(bad_utf8.input_error, ":3: byte \\x87 is not valid UTF-8");
  // Inside strings and comments they are valid TOML and stay accepted.
  const fs::path corpus = fs::path(BEAMPACK_FUZZ_DIR) / "corpus" / "run_config";
  EXPECT_TRUE(check_run_file(bytes_of(corpus / "non_ascii_in_strings.toml")).accepted);
}

}  // namespace
}  // namespace beampack::fuzz
