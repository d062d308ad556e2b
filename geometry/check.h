#pragma once
// Invariants on hot paths (STYLE.md point 7), compiled in only with BEAMPACK_CHECKS: the
// sanitizer build (scripts/sanitize.sh, which runs the whole test suite with them) and any
// -DBEAMPACK_CHECKS=ON or Debug build. Elsewhere a check is nothing: its condition (an operand
// of sizeof, so its variables count as used) and its facts are not evaluated, so the release hot
// paths pay nothing for them.
//
// A failed check prints the broken condition, where it is, the facts the call site gives (ray,
// particle, values) and how to reproduce it (the run's step and seeds, from check_context),
// then aborts: an invariant that fails is a bug in beampack, not bad input.
#include <string>

namespace beampack {

// What a failed check prints to say how to reproduce it; the simulation sets it at each step.
// Empty outside a simulation (a library call, a test).
void set_check_context(std::string text);
std::string check_context();

[[noreturn]] void check_failed(const char* condition, const char* file, int line,
                               const std::string& facts);

// printf-style facts for a failed check, formatted only when it fails.
std::string check_facts(const char* format, ...) __attribute__((format(printf, 1, 2)));

}  // namespace beampack

#ifdef BEAMPACK_CHECKS
#define BEAMPACK_CHECKS_ON 1
#define BEAMPACK_DCHECK(condition, ...)                               \
  do {                                                                \
    if (!(condition))                                                 \
      ::beampack::check_failed(#condition, __FILE__, __LINE__,        \
                               ::beampack::check_facts(__VA_ARGS__)); \
  } while (0)
#else
#define BEAMPACK_CHECKS_ON 0
#define BEAMPACK_DCHECK(condition, ...) \
  do {                                  \
    (void)sizeof(!(condition));         \
  } while (0)
#endif
