// beampack: the command line (INTERFACE.md). Exit codes: 0 success, 1 failed run, 2 bad input,
// 128 + N stopped by signal N (130: Ctrl-C), as the help's footer says.
#include <CLI/CLI.hpp>
#include <cctype>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <exception>
#include <filesystem>
#include <iostream>

#include "engine/build_info.h"
#include "geometry/error.h"
#include "tools/converge.h"
#include "tools/run_command.h"
#include "tools/stability.h"
#include "tools/validate.h"

namespace {

using namespace beampack::tools;

// An empty --preset would read as none given: the built-in defaults, silently.
const CLI::Validator kNamed(
    [](const std::string& s) {
  return s.empty() ? std::string("must name a preset (beampack presets)") : "";
    },
    "NAME");

// A count is checked as a whole number before its range: CLI11's Range reads 2.5 as a number and
// said "not in range 0 to 4096" of it.
const CLI::Validator kWhole(
    [](std::string& text) -> std::string {
      const std::size_t first = text.starts_with('+') ? 1 : 0;  // "+2" is 2, as CLI11 reads it
      const bool digits =
          text.size() > first && text.find_first_not_of("0123456789", first) == std::string::npos;
      return digits ? "" : "Value " + text + " is not a whole number >= 0";
    },
    "WHOLE");

// A run file named `-` is standard input (`beampack config | beampack run -`), as /dev/stdin is.
const CLI::Validator kDashIsStdin(
    [](std::string& name) {
  if (name == "-") name = "/dev/stdin";
  return std::string();
    },
    "", "-");

void add_run_sources(CLI::App* cmd, RunOptions& o) {
  cmd->add_option("run_file", o.sources.file, "run file (TOML; - reads standard input)")
      ->transform(kDashIsStdin)
      ->check(CLI::ExistingFile);
  cmd->add_option("--preset", o.sources.preset, "start from a named preset (beampack presets)")
      ->check(kNamed);
  // One value per --set: a run file after it is not taken as a second assignment.
  cmd->add_option("--set", o.sources.sets, "override one key: --set material.conductivity=100")
      ->allow_extra_args(false);
}

// What run, sweep and converge share: the scene's sources, then --out, --threads and --quiet.
void add_run_options(CLI::App* cmd, RunOptions& o) {
  add_run_sources(cmd, o);
  cmd->add_option("--out", o.out_dir, "output directory")->capture_default_str();
  cmd->add_option("--threads", o.threads, "worker threads (0: all cores)")
      ->check(kWhole)
      ->check(CLI::Range(0, 4096));
  cmd->add_flag("--quiet", o.quiet, "no progress line");
}

// The command named by the first argument, if there is one.
const CLI::App* command_named(const CLI::App& app, int argc, char** argv) {
  if (argc < 2) return nullptr;
  for (const CLI::App* sub : app.get_subcommands({}))
    if (sub->get_name() == argv[1]) return sub;
  return nullptr;
}

// "a, b, c"
std::string listed(const std::vector<std::string>& names) {
  std::string text;
  for (const std::string& name : names) text += (text.empty() ? "" : ", ") + name;
  return text;
}

// CLI11 answers an unknown first word with "A subcommand is required": name it instead.
bool unknown_command(const CLI::App& app, int argc, char** argv) {
  if (argc < 2 || argv[1][0] == '-' || command_named(app, argc, argv)) return false;
  std::vector<std::string> names;
  for (const CLI::App* sub : app.get_subcommands({})) names.push_back(sub->get_name());
  std::fprintf(stderr, "beampack: error: unknown command `%s`%s (commands: %s)\n", argv[1],
               did_you_mean(argv[1], names).c_str(), listed(names).c_str());
  return true;
}

// CLI11 hands an option the command does not have to the parent, and its value then fails as the
// run file ("run_file: File does not exist: 1"): name the option instead. Likewise a
// space-separated --values list (`--values 0 10 100`), whose second value would be read as the
// run file.
bool misread_arguments(const CLI::App& app, int argc, char** argv) {
  const CLI::App* sub = command_named(app, argc, argv);
  if (!sub) return false;
  for (int k = 2; k < argc; ++k) {
    const std::string token = argv[k];
    const bool number =
        token.size() > 1 && (std::isdigit(static_cast<unsigned char>(token[1])) || token[1] == '.');
    if (token == "--") break;
    if (token.size() > 1 && token[0] == '-' && !number) {
      const std::string name = token.substr(0, token.find('='));
      if (name == "-h" || name == "--help" || sub->get_option_no_throw(name)) continue;
      std::vector<std::string> names;
      for (const CLI::Option* o : sub->get_options())
        if (!o->get_lnames().empty()) names.push_back("--" + o->get_lnames().front());
      std::fprintf(stderr, "beampack: error: `%s` has no option %s%s (its options: %s)\n", argv[1],
                   name.c_str(), did_you_mean(name, names).c_str(), listed(names).c_str());
      return true;
    }
    const bool after_values = k >= 4 && std::string(argv[k - 2]) == "--values";
    if (after_values && !token.empty() && token[0] != '-' &&
        std::isdigit(static_cast<unsigned char>(token[0])) && !std::filesystem::exists(token)) {
      std::fprintf(
          stderr,
          "beampack: error: --values takes one comma-separated argument (--values %s,%s,...): "
          "`%s` would be read as the run file\n",
          argv[k - 1], token.c_str(), token.c_str());
      return true;
    }
  }
  return false;
}

int list_presets() {
  for (const Preset& p : presets()) std::printf("%-12s %s\n", p.name, p.summary);
  return 0;
}

int print_config(RunSources sources) {
  sources.xi_always_read = true;  // the run file printed may be converge's
  const RunConfig config = load_run_config(sources);
  warn_of_input({&config});
  std::cout << run_file_text(config);
  return 0;
}

// Standard output closed by the caller (`>&-`): held open on /dev/null, what goes there is lost.
bool stdout_closed = false;

// Why what was printed did not all reach standard output; "" when it did.
std::string stdout_loss() {
  std::cout.flush();
  if (stdout_closed) return "is closed";
  if (std::cout && std::fflush(stdout) == 0 && !std::ferror(stdout)) return "";
  return std::string("could not be written (") + std::strerror(errno) + ")";
}

// What validate, presets and config print is their product: one that could not be written (a
// full disk, a closed pipe, /dev/full) is a failed command, not an empty success.
int output_written(int code) {
  const std::string loss = stdout_loss();
  if (loss.empty()) return code;
  std::fprintf(stderr, "beampack: error: standard output %s\n", loss.c_str());
  return code == 0 ? 1 : code;
}

// run, sweep and converge: their results are the --out folder's files; a printed table that
// standard output could not take (/dev/full, a reader that stopped early) is said to be lost.
int table_written(int code) {
  const std::string loss = stdout_loss();
  if (!loss.empty())
    std::fprintf(stderr,
                 "beampack: warning: standard output %s: the printed lines are lost; what the "
                 "command wrote is in its --out folder\n",
                 loss.c_str());
  return code;
}

}  // namespace

int main(int argc, char** argv) {
  stdout_closed = keep_standard_streams_open();
  install_interrupt_handler();
  CLI::App app{"beampack: laser processing of packed powders (Zohdi 2013)", "beampack"};
  app.require_subcommand(1);
  app.footer(
      "Exit codes: 0 done, 1 a failed run, 2 bad input, 128 + N stopped by signal N (130 for "
      "Ctrl-C: `beampack run --resume DIR` goes on).");
  const beampack::BuildInfo built = beampack::build_info();
  app.set_version_flag("--version", std::string("beampack ") + built.version + " (git " +
                                        built.revision + ", " + built.build_type + ", " +
                                        built.compiler + ", flags \"" + built.flags + "\")");
  RunOptions run;
  SweepOptions sweep;
  bool quiet_validate = false;

  CLI::App* run_cmd = app.add_subcommand("run", "run one scene and write its outputs");
  add_run_options(run_cmd, run);
  run_cmd
      ->add_option("--checkpoint-every", run.checkpoint_every,
                   "write DIR/checkpoint.bin every N pulses (atomically)")
      ->check(kWhole)
      ->check(CLI::Range(0, 1'000'000'000));
  run_cmd->add_option("--resume", run.resume, "continue the run whose checkpoint is in DIR")
      ->check(CLI::ExistingDirectory);

  CLI::App* sweep_cmd = app.add_subcommand("sweep", "one run per value of a parameter");
  add_run_options(sweep_cmd, sweep.run);
  sweep_cmd->add_option("--param", sweep.param, "key to vary")->required();
  // Split by sweep_command itself, which refuses an empty value instead of dropping it.
  sweep_cmd
      ->add_option("--values", sweep.values,
                   "comma-separated values, one argument: --values 0,10,100")
      ->required()
      ->allow_extra_args(false)
      ->type_name("V1,V2,...");

  RunOptions converge;
  CLI::App* converge_cmd =
      app.add_subcommand("converge", "error against run time over resolution ladders");
  add_run_options(converge_cmd, converge);

  CLI::App* validate_cmd =
      app.add_subcommand("validate", "run the analytic cases and print a table");
  validate_cmd->add_flag("--quiet", quiet_validate, "print failures only");
  bool stiff = false;
  CLI::Option* stiff_flag = validate_cmd->add_flag(
      "--stiff", stiff, "run the stability grid (K, dt, index, N, phi, solver, scene) instead");
  std::vector<std::string> only;
  validate_cmd
      ->add_option("--only", only,
                   "with --stiff, the cells whose COLUMN has one of the values (repeatable: all "
                   "at once)")
      ->type_name("COLUMN=V[,V...]")
      ->allow_extra_args(false)
      ->needs(stiff_flag);

  app.add_subcommand("presets", "list the named presets");
  RunOptions config;
  CLI::App* config_cmd = app.add_subcommand("config", "print a complete run file");
  config_cmd->add_option("--preset", config.sources.preset, "preset to print")->check(kNamed);
  config_cmd->add_option("run_file", config.sources.file, "run file to resolve (- reads stdin)")
      ->transform(kDashIsStdin)
      ->check(CLI::ExistingFile);
  config_cmd->add_option("--set", config.sources.sets, "override one key")->allow_extra_args(false);

  if (unknown_command(app, argc, argv) || misread_arguments(app, argc, argv)) return 2;
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    if (e.get_exit_code() == static_cast<int>(CLI::ExitCodes::Success))
      return app.exit(e);  // --help, --version
    // In the words of every other refusal (CLI11's own: "run_file: File does not exist: x").
    std::fprintf(stderr, "beampack: error: %s (--help lists the options)\n", e.what());
    return 2;
  }
  try {
    if (run_cmd->parsed()) {
      run.out_set = run_cmd->count("--out") > 0;
      run.checkpoint_set = run_cmd->count("--checkpoint-every") > 0;
      return exit_code(table_written(run_command(run)));
    }
    if (sweep_cmd->parsed()) return exit_code(table_written(sweep_command(sweep)));
    if (converge_cmd->parsed()) return exit_code(table_written(converge_command(converge)));
    if (validate_cmd->parsed() && stiff)
      return output_written(run_stability_report(quiet_validate, only));
    if (validate_cmd->parsed()) {  // a fraction of a second: an interrupt is answered at its end
      const int code = output_written(run_validate(quiet_validate));
      return code == 0 && stop_requested().load() ? interrupted_exit_code() : code;
    }
    if (app.got_subcommand("presets")) return output_written(list_presets());
    if (config_cmd->parsed()) return output_written(print_config(config.sources));
  } catch (const beampack::InputError& e) {
    std::fprintf(stderr, "beampack: error: %s\n", e.what());
    return exit_code(2);  // a set-up left running on its thread must not see the static destructors
  } catch (const std::exception& e) {
    std::fprintf(stderr, "beampack: run failed: %s\n", e.what());
    return exit_code(1);
  }
  return 0;
}
