#pragma once
// Long cases (suites named *Long) run only when asked: BEAMPACK_LONG=1 (README, "Tests"). Any
// other value, 0 included, leaves them out, in every suite alike.
#include <cstdlib>
#include <string_view>

namespace beampack::test {

inline bool long_tests_asked() {
  const char* value = std::getenv("BEAMPACK_LONG");
  return value != nullptr && std::string_view(value) == "1";
}

}  // namespace beampack::test
