#pragma once
// Refusals checked in one place. An error of a type other than the one asked for escapes to fail
// the test.
#include <gtest/gtest.h>

#include <functional>
#include <string>
#include <string_view>

namespace beampack::testing {

// Whether `text` holds `part`; a failure shows both, whole.
inline ::testing::AssertionResult contains(const char* text_expr, const char* part_expr,
                                           std::string_view text, std::string_view part) {
  if (text.find(part) != std::string_view::npos) return ::testing::AssertionSuccess();
  return ::testing::AssertionFailure() << text_expr << " does not hold " << part_expr
                                       << "\n  text: " << text << "\n  part: " << part;
}

inline ::testing::AssertionResult lacks(const char* text_expr, const char* part_expr,
                                        std::string_view text, std::string_view part) {
  const std::size_t at = text.find(part);
  if (at == std::string_view::npos) return ::testing::AssertionSuccess();
  return ::testing::AssertionFailure() << text_expr << " holds " << part_expr << " at " << at
                                       << "\n  text: " << text << "\n  part: " << part;
}

#define EXPECT_CONTAINS(text, part) EXPECT_PRED_FORMAT2(::beampack::testing::contains, text, part)
#define ASSERT_CONTAINS(text, part) ASSERT_PRED_FORMAT2(::beampack::testing::contains, text, part)
#define EXPECT_NOT_CONTAINS(text, part) EXPECT_PRED_FORMAT2(::beampack::testing::lacks, text, part)
#define ASSERT_NOT_CONTAINS(text, part) ASSERT_PRED_FORMAT2(::beampack::testing::lacks, text, part)

// What error_message gives for a call that returns.
inline constexpr const char kAccepted[] = "(accepted)";

// `call` throws an E whose message holds every one of `fragments`; a call that returns fails the
// test, naming the fragments it expected.
template <class E, class... Fragments>
void expect_error(const std::function<void()>& call, const Fragments&... fragments) {
  static_assert(sizeof...(Fragments) > 0, "expect_error: name at least one fragment");
  const std::string_view parts[] = {std::string_view(fragments)...};
  try {
    call();
  } catch (const E& e) {
    const std::string what = e.what();
    for (const std::string_view part : parts) EXPECT_CONTAINS(what, part);
    return;
  }
  std::string expected;
  for (const std::string_view part : parts)
    expected += (expected.empty() ? "\"" : ", \"") + std::string(part) + "\"";
  ADD_FAILURE() << "accepted; expected an error naming " << expected;
}

// The message of the E that `call` throws, or kAccepted when it returns.
template <class E>
std::string error_message(const std::function<void()>& call) {
  try {
    call();
  } catch (const E& e) {
    return e.what();
  }
  return kAccepted;
}

}  // namespace beampack::testing
