#pragma once
// Run-file parameters read through one typed accessor that records which keys were used
// (pbrt's ReportUnused, Mitsuba's unqueried): an unknown or misspelled key is an error naming its
// file and line. Every message names the key, the value and the limit.
#include <algorithm>
#include <cstdint>
#include <initializer_list>
#include <limits>
#include <map>
#include <set>
#include <string>
#include <vector>

#include <toml++/toml.h>

namespace beampack::tools {

// Which layer set a key: "file:line", "--set KEY=VALUE" or "preset NAME"; the run file's path
// (run files only); and the layer's rank (later layers override earlier ones).
struct KeyOrigin {
  std::string at, file;
  int layer = 0;
  bool command_line = false;  // a --set (or a swept value): what the user asked for in this run
  bool swept = false;         // a value of sweep's --param or of a converge ladder
};

// A run file's bytes, checked as merge_toml_file checks them (not a FIFO or device, at most 16 MiB,
// without a UTF-8 byte-order mark).
std::string read_run_file(const std::string& path);

class Params {
 public:
  Params() = default;
  // Layers apply in order: later ones override earlier ones key by key.
  void merge_toml_text(const std::string& text, const std::string& source);  // preset
  // The run file at `path`; with `bytes`, those read from it before (read_run_file), so that a
  // command that resolves it several times reads a pipe, or a file being edited, once.
  void merge_toml_file(const std::string& path, const std::string* bytes = nullptr);
  // A run file merged that set no key (empty, or comments only): "" when there is none.
  const std::string& empty_file() const { return empty_file_; }
  // --set KEY=VALUE; `origin` names it in messages (default "--set KEY=VALUE"); `swept` for a
  // value of sweep's --param or of a converge ladder.
  void merge_assignment(const std::string& key_equals_value, const std::string& origin = "",
                        bool swept = false);

  // A number in [lo, hi], or with lo_open / hi_open the interval open at that end.
  // stated_hi: an upper limit the caller enforces itself (with its own reason), stated in this
  // message too so that a value below lo is told the whole range.
  double number(const std::string& key, double fallback, double lo, double hi, bool lo_open = false,
                bool hi_open = false, double stated_hi = std::numeric_limits<double>::max());
  // A number >= lo, or exactly `special` (standing for `meaning`), every refusal stating both;
  // stated_hi as for number(). A range from `special` up would admit the values between.
  double number_or(const std::string& key, double fallback, double lo, double stated_hi,
                   double special, const std::string& meaning);
  std::int64_t integer(const std::string& key, std::int64_t fallback, std::int64_t lo,
                       std::int64_t hi);
  std::string text(const std::string& key, const std::string& fallback);
  std::string choice(const std::string& key, const std::string& fallback,
                     std::initializer_list<const char*> allowed);
  bool flag(const std::string& key, bool fallback);
  bool has(const std::string& key) const;
  // A file path, made absolute: a relative one from a run file is taken from the run file's
  // folder, from --set from the working directory.
  std::string path(const std::string& key);
  // Whether `later` was set by a later layer than `earlier` (both set, `earlier` not from the
  // command line: two --set that contradict each other are refused, whatever their order).
  bool set_later(const std::string& later, const std::string& earlier) const;
  // Whether --set (or a sweep) gave the key: what the user asked for in this run.
  bool set_on_command_line(const std::string& key) const;
  // Where the key's value came from, for a message about another key: "run.toml:12",
  // "--set KEY=VALUE", "preset quick", or "the default".
  std::string source_of(const std::string& key) const;
  // Whether the key's value is a swept one (sweep's --param, a converge ladder).
  bool swept(const std::string& key) const;
  // Whether a run file (not a preset, a checkpoint or --set) gave the key its value.
  bool set_in_run_file(const std::string& key) const;
  // Whether a number read by number() or integer() differs from the fallback it was read with
  // (true for a key read otherwise): a default a file merely carries from `beampack config` does
  // not (a preset's own value, such as quick's seed 7, does differ).
  bool differs_from_default(const std::string& key) const;
  // The value a key was read as (after its accessor), as messages show it: 7, "flat".
  std::string shown(const std::string& key) const;
  // Drops a key from the layers, as if none had set it.
  void forget(const std::string& key);
  // Every key a layer set, with where: RunConfig keeps them to locate errors found later.
  std::map<std::string, std::string> origins() const;
  // A number, or one of the given words (`thermal.dt = "pulse"`, `pulses.period = "auto"`).
  // Returns the word, or "" and sets value. `unit` names the number's unit in the error message;
  // lo itself is allowed only when lo_open is false.
  std::string number_or_word(const std::string& key, double& value, double lo, double hi,
                             std::initializer_list<const char*> words,
                             const std::string& fallback_word, const std::string& unit = "seconds",
                             bool lo_open = true,
                             double stated_hi = std::numeric_limits<double>::max());

  // InputError for the first key present in the layers but never read.
  void check_all_used() const;
  // InputError "<file>:<line>: `key` = value: limit" (the line when a layer set the key): for
  // checks beyond a key's own range, such as one key against another.
  [[noreturn]] void fail(const std::string& key, const std::string& value,
                         const std::string& limit) const;
  // Every key read, with the value used (defaults included): `beampack config` and summary.json.
  const toml::table& resolved() const { return resolved_; }

 private:
  const toml::node* find(const std::string& key) const;
  std::string quoting_hint(const std::string& key, const toml::node& node) const;
  // A number node's value as a double (a whole number too, beyond 2^53), refused with `range`
  // when it is no number or not finite.
  double number_value(const std::string& key, const toml::node& node,
                      const std::string& range) const;
  std::map<std::string, std::string> raw_values_;  // key -> its last --set value, as typed
  const KeyOrigin* origin(const std::string& key) const;
  std::string where(const std::string& key) const;  // "run.toml:12: " or "--set: " or ""
  void record(const std::string& key, toml::node&& value);

  toml::table merged_;
  std::map<std::string, KeyOrigin> origin_;  // key -> the layer that set it
  int layers_ = 0;
  std::string empty_file_;  // a run file that set no key ("" when none did)
  std::set<std::string> used_;
  toml::table resolved_;
  // key -> fallback of number() and integer(), and of flag() as 0 or 1
  std::map<std::string, double> number_defaults_;
};

// `s` without the spaces and tabs at either end.
std::string trimmed(const std::string& s);
// `v = VALUE` parsed as a `--set` is, through the run files' own checks (invalid UTF-8, non-ASCII
// bytes where toml++ 3.3 reaches undefined behaviour, numbers that underflow to 0): throws a
// std::runtime_error (toml::parse_error or InputError) where TOML reads no value there, as for a
// bare word, which a run takes as a string.
toml::table parsed_value(const std::string& value, const std::string& source);
// The key a `--set KEY=VALUE` sets, as the run file reads it: `--set "k = v"` sets k.
std::string assignment_key(const std::string& key_equals_value);

// Levenshtein distance: insertions, deletions and substitutions of one character.
std::size_t edit_distance(const std::string& a, const std::string& b);
// " (did you mean `run`?)" for the name among `names` nearest to `typed`, the first of equals,
// where it is within three edits and a third of `typed`'s length (at least one): "" when none
// is, as for `frob`, three edits from `run`. For a mistyped key, command or option.
template <class Names>
std::string did_you_mean(const std::string& typed, const Names& names) {
  const std::string* best = nullptr;
  std::size_t best_d = std::min<std::size_t>(3, std::max<std::size_t>(1, typed.size() / 3)) + 1;
  for (const std::string& name : names)
    if (const std::size_t d = edit_distance(typed, name); d < best_d) best_d = d, best = &name;
  return best ? " (did you mean `" + *best + "`?)" : "";
}

// Dotted keys of every leaf in a table ("material.conductivity").
std::vector<std::string> leaf_keys(const toml::table& table, const std::string& prefix = "");

}  // namespace beampack::tools
