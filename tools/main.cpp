// beampack: the command line (INTERFACE.md). Exit codes: 0 success, 1 failed run, 2 bad input.
#include <CLI/CLI.hpp>

#include <cstdio>
#include <exception>

#include "geometry/error.h"
#include "tools/validate.h"

int main(int argc, char** argv) {
  CLI::App app{"beampack: laser processing of packed powders (Zohdi 2013)", "beampack"};
  app.require_subcommand(1);
  bool quiet = false;
  CLI::App* validate = app.add_subcommand("validate", "run the analytic cases and print a table");
  validate->add_flag("--quiet", quiet, "print failures only");
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int code = app.exit(e);
    return code == 0 ? 0 : 2;
  }
  try {
    if (validate->parsed()) return beampack::tools::run_validate(quiet);
  } catch (const beampack::InputError& e) {
    std::fprintf(stderr, "beampack: error: %s\n", e.what());
    return 2;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "beampack: run failed: %s\n", e.what());
    return 1;
  }
  return 0;
}
