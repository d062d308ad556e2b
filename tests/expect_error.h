#pragma once
// A refusal checked in one place: `call` throws an E whose message holds `fragment`; a call that
// returns fails the test, and an error of another type escapes to fail it too.
#include <gtest/gtest.h>

#include <functional>
#include <string>

namespace beampack::testing {

template <class E>
void expect_error(const std::function<void()>& call, const std::string& fragment) {
  try {
    call();
    ADD_FAILURE() << "accepted; expected: " << fragment;
  } catch (const E& e) {
    EXPECT_NE(std::string(e.what()).find(fragment), std::string::npos) << e.what();
  }
}

}  // namespace beampack::testing
