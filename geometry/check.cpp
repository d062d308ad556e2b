#include "geometry/check.h"

#include <cstdarg>
#include <cstdio>
#include <cstdlib>
#include <mutex>

namespace beampack {
namespace {

std::mutex context_mutex;
std::string context_text;

}  // namespace

void set_check_context(std::string text) {
  const std::lock_guard lock(context_mutex);
  context_text = std::move(text);
}

std::string check_context() {
  const std::lock_guard lock(context_mutex);
  return context_text;
}

std::string check_facts(const char* format, ...) {
  char text[512];
  va_list args;
  va_start(args, format);
  std::vsnprintf(text, sizeof text, format, args);
  va_end(args);
  return text;
}

void check_failed(const char* condition, const char* file, int line, const std::string& facts) {
  const std::string context = check_context();
  std::fprintf(
      stderr,
      "beampack: internal check failed at %s:%d: %s\n  %s\n  to reproduce: %s, with a build "
      "made with -DBEAMPACK_CHECKS=ON; please report it with the run file\n",
      file, line, condition, facts.c_str(),
      context.empty() ? "the same run file or call (before a simulation's first step)"
                      : context.c_str());
  std::fflush(stderr);
  std::abort();
}

}  // namespace beampack
