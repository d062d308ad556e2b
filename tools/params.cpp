#include "tools/params.h"

#include <algorithm>
#include <array>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <sstream>

#include "geometry/error.h"
#include "geometry/input_file.h"

namespace beampack::tools {
namespace {

std::vector<std::string> split_key(const std::string& key) {
  std::vector<std::string> parts;
  std::stringstream s(key);
  for (std::string part; std::getline(s, part, '.');) parts.push_back(part);
  return parts;
}

void set_path(toml::table& root, const std::string& key, const toml::node& value) {
  const auto parts = split_key(key);
  toml::table* t = &root;
  for (std::size_t k = 0; k + 1 < parts.size(); ++k) {
    toml::node* child = t->get(parts[k]);
    if (!child || !child->is_table()) t->insert_or_assign(parts[k], toml::table{});
    t = t->get(parts[k])->as_table();
  }
  value.visit([&](auto&& concrete) { t->insert_or_assign(parts.back(), concrete); });
}

std::string repr(const toml::node& node) {
  std::ostringstream s;
  if (const toml::table* t = node.as_table()) {  // inline: `{ a = 1 }`, not a table's lines
    toml::table copy = *t;
    copy.is_inline(true);
    s << copy;
    return s.str();
  }
  node.visit([&](auto&& concrete) { s << concrete; });
  return s.str();
}

}  // namespace

std::vector<std::string> leaf_keys(const toml::table& table, const std::string& prefix) {
  std::vector<std::string> keys;
  for (const auto& [k, node] : table) {
    const std::string key =
        prefix.empty() ? std::string(k.str()) : prefix + "." + std::string(k.str());
    if (const toml::table* sub = node.as_table(); sub && !sub->empty()) {
      const auto inner = leaf_keys(*sub, key);
      keys.insert(keys.end(), inner.begin(), inner.end());
    } else {
      keys.push_back(key);
    }
  }
  return keys;
}

namespace {

// Records that `source` set `key`. Its value replaces whatever the merged table held on its path
// (set_path): a value above it (`k.a = 2` over `k = 1` turns k into a table) and the keys under it
// (`k = 1` over `k.a = 2`), so their origins go too: a message then names the layer whose value is
// there now, not an older one that set the key before it was overridden.
void set_origin(std::map<std::string, KeyOrigin>& origin, const std::string& key,
                const KeyOrigin& source) {
  for (std::size_t dot = key.find('.'); dot != std::string::npos; dot = key.find('.', dot + 1))
    origin.erase(key.substr(0, dot));
  const std::string below = key + ".";
  for (auto it = origin.lower_bound(below); it != origin.end() && it->first.starts_with(below);)
    it = origin.erase(it);
  origin[key] = source;
}

// Walks the layer's own tables (not dotted paths: a quoted key such as "a.b", "" or "x[0]" is
// one TOML key that a path lookup cannot find; fuzz/ found the null dereference that caused).
// Such names cannot be run-file keys, whose parts are bare words joined by dots.
void merge_layer(toml::table& merged, std::map<std::string, KeyOrigin>& origin,
                 const toml::table& layer, const KeyOrigin& source, bool with_lines,
                 const std::string& prefix = "");

// One key's value from a layer, `at` where the layer gave it. A table sets its keys, as a run
// file's [material] does: the keys it leaves out keep the values earlier layers gave them.
void merge_value(toml::table& merged, std::map<std::string, KeyOrigin>& origin,
                 const std::string& key, const toml::node& node, const KeyOrigin& source,
                 bool with_lines, const std::string& at) {
  if (const toml::table* sub = node.as_table(); sub && !sub->empty()) {
    merge_layer(merged, origin, *sub, source, with_lines, key);
    return;
  }
  // An empty table sets no key, but it must not vanish: `[foo]` is an unknown key, and
  // `[beam.rays]` or `rays = {}` a wrong type (check_all_used, the typed accessors). It never
  // clears a table an earlier layer filled (`[beam]` with its keys commented out).
  if (node.is_table() && merged.at_path(key).is_table()) return;
  set_path(merged, key, node);
  KeyOrigin here = source;
  here.at = at;
  set_origin(origin, key, here);
}

void merge_layer(toml::table& merged, std::map<std::string, KeyOrigin>& origin,
                 const toml::table& layer, const KeyOrigin& source, bool with_lines,
                 const std::string& prefix) {
  for (const auto& [k, node] : layer) {
    const std::string name(k.str());
    const std::string at =
        with_lines ? source.at + ":" + std::to_string(node.source().begin.line) : source.at;
    if (name.empty() || name.find_first_of(".[]") != std::string::npos)
      throw InputError(at + ": key \"" + name + "\" (under `" + prefix +
                       "`): run-file key names are bare words, without '.', '[' or ']'");
    merge_value(merged, origin, prefix.empty() ? name : prefix + "." + name, node, source,
                with_lines, at);
  }
}

// TOML files must be valid UTF-8, and toml++ 3.3 reaches undefined behaviour on some invalid
// sequences inside strings (fuzz/regressions/run_config/invalid_utf8_in_string.toml):
// refuse overlong forms, surrogates, code points above U+10FFFF and stray bytes first.
// Where text stops being valid UTF-8 (npos: nowhere).
std::size_t first_invalid_utf8(std::string_view text) {
  for (std::size_t i = 0; i < text.size();) {
    const auto b = static_cast<unsigned char>(text[i]);
    if (b < 0x80) {
      ++i;
      continue;
    }
    const int extra = b >= 0xF0 && b <= 0xF4   ? 3
                      : b >= 0xE0 && b <= 0xEF ? 2
                      : b >= 0xC2 && b <= 0xDF ? 1
                                               : -1;
    std::uint32_t cp = extra == 3 ? b & 0x07u : extra == 2 ? b & 0x0Fu : b & 0x1Fu;
    bool ok = extra > 0 && i + std::size_t(extra) < text.size();
    for (int k = 1; ok && k <= extra; ++k) {
      const auto c = static_cast<unsigned char>(text[i + k]);
      ok = (c & 0xC0) == 0x80;
      cp = (cp << 6) | (c & 0x3Fu);
    }
    ok = ok && !(extra == 2 && cp < 0x800) && !(extra == 3 && (cp < 0x10000 || cp > 0x10FFFF)) &&
         !(cp >= 0xD800 && cp <= 0xDFFF);
    if (!ok) return i;
    i += std::size_t(extra) + 1;
  }
  return std::string_view::npos;
}

// A path for a message: bytes outside printable ASCII as \xNN (the terminal may not show them).
std::string bytes_shown(std::string_view text) {
  std::string out = "\"";
  for (const char c : text) {
    const auto b = static_cast<unsigned char>(c);
    out += b >= 0x20 && b < 0x7F ? std::string(1, c) : escaped_byte(b);
  }
  return out + "\"";
}

void reject_invalid_utf8(std::string_view text, const std::string& source) {
  const std::size_t at = first_invalid_utf8(text);
  if (at == std::string_view::npos) return;
  const auto line = 1 + std::count(text.begin(), text.begin() + std::ptrdiff_t(at), '\n');
  throw InputError(source + ":" + std::to_string(line) + ": byte " +
                   escaped_byte(static_cast<unsigned char>(text[at])) +
                   " is not valid UTF-8 (TOML files must be UTF-8)");
}

// The code point of the (already validated) UTF-8 sequence at text[i]; advances i past it.
std::uint32_t decode_utf8(std::string_view text, std::size_t& i) {
  const auto b = static_cast<unsigned char>(text[i]);
  const int extra = b >= 0xF0 ? 3 : b >= 0xE0 ? 2 : 1;
  std::uint32_t cp = b & (0x3Fu >> extra);
  for (int k = 1; k <= extra; ++k)
    cp = (cp << 6) | (static_cast<unsigned char>(text[i + k]) & 0x3Fu);
  i += std::size_t(extra) + 1;
  return cp;
}

// The text toml++ is given holds no byte above 0x7F outside comments: toml++ 3.3 (Debian) tests
// such bytes as possible whitespace while it scans a token, and its Unicode table reaches
// __builtin_unreachable (undefined behaviour) in is_non_ascii_horizontal_whitespace() for most
// code points in U+00A1..U+0499, U+2FCE..U+33C7 and U+FE5E..U+FEFE (found by fuzz/). Where it would
// scan is not always where a string seems to start (`a = 0"""è"` is a bare token to it), so no
// non-ASCII byte may reach it there: in basic strings each character becomes its \uXXXX escape (the
// same string in TOML), in literal strings (no escapes) and between tokens it is refused, naming
// the line.
std::string ascii_for_toml(std::string_view text, const std::string& source) {
  enum { normal, comment, basic, literal, multi_basic, multi_literal } state = normal;
  std::size_t line = 1;
  std::string out;
  out.reserve(text.size());
  auto quotes_at = [&](std::size_t i, char q) {
    return i + 2 < text.size() && text[i] == q && text[i + 1] == q && text[i + 2] == q;
  };
  auto refuse = [&](std::size_t i, const char* where) {
    std::string bytes;
    for (std::size_t j = i;
         j < text.size() && j < i + 4 && static_cast<unsigned char>(text[j]) >= 0x80; ++j)
      bytes += escaped_byte(static_cast<unsigned char>(text[j]));
    throw InputError(source + ":" + std::to_string(line) + ": unexpected character " + bytes + " " +
                     where);
  };
  for (std::size_t i = 0; i < text.size();) {
    const char ch = text[i];
    if (static_cast<unsigned char>(ch) >= 0x80) {
      if (state == normal) refuse(i, "outside a string or comment (TOML allows only ASCII there)");
      if (state == literal || state == multi_literal)
        refuse(i,
               "in a literal string: write it in a \"...\" string (beampack reads non-ASCII only "
               "there)");
      if (state == comment) {
        out += ch;
        ++i;
        continue;
      }
      char escaped[16];
      const std::uint32_t cp = decode_utf8(text, i);
      std::snprintf(escaped, sizeof escaped, cp > 0xFFFF ? "\\U%08X" : "\\u%04X", cp);
      out += escaped;
      continue;
    }
    if (ch == '\n') ++line;
    out += ch;
    switch (state) {
      case normal:
        if (ch == '#') state = comment;
        else if (quotes_at(i, '"')) state = multi_basic, out += "\"\"", i += 2;
        else if (quotes_at(i, '\'')) state = multi_literal, out += "''", i += 2;
        else if (ch == '"') state = basic;
        else if (ch == '\'') state = literal;
        break;
      case comment:
        if (ch == '\n') state = normal;
        break;
      case basic:
      case multi_basic:
        if (ch == '\\' && i + 1 < text.size()) {  // an escape: its next byte is taken as it is
          if (static_cast<unsigned char>(text[i + 1]) >= 0x80)
            refuse(i + 1, "after a backslash (not an escape)");
          line += text[i + 1] == '\n';
          out += text[++i];
        } else if (state == basic && (ch == '"' || ch == '\n')) {
          state = normal;
        } else if (state == multi_basic && quotes_at(i, '"')) {
          // Up to two quotes may end the content right before the closing three.
          while (i + 1 < text.size() && text[i + 1] == '"') out += text[++i];
          state = normal;
        }
        break;
      case literal:
        if (ch == '\'' || ch == '\n') state = normal;
        break;
      case multi_literal:
        if (quotes_at(i, '\'')) {
          while (i + 1 < text.size() && text[i + 1] == '\'') out += text[++i];
          state = normal;
        }
        break;
    }
    ++i;
  }
  return out;
}

constexpr const char* kUnderflow = "underflows to 0 (nonzero numbers must be >= 2.2e-308 in size)";

// A number written beyond the doubles' range: +1 above it (1e400: the TOML parser refuses it, so
// it reaches the reader as text), -1 below it (1e-400: the parser rounds it to 0 without a
// word), 0 within it or not a number.
// TOML allows underscores between digits (1e-4_00 is 1e-400), strtod does not: they are dropped.
int beyond_doubles(const std::string& written) {
  std::string token = written;
  std::erase(token, '_');
  char* end = nullptr;
  errno = 0;
  const double v = std::strtod(token.c_str(), &end);
  if (token.empty() || *end != 0 || errno != ERANGE) return 0;
  return std::isfinite(v) ? -1 : 1;
}

bool underflows(const std::string& token) {
  return beyond_doubles(token) < 0;
}

// Every 0.0 of a parsed file whose written token underflowed is refused, with its line.
void reject_underflow(const toml::node& node, const std::vector<std::string_view>& lines,
                      const std::string& source) {
  if (const toml::table* t = node.as_table()) {
    for (const auto& [key, child] : *t) reject_underflow(child, lines, source);
  } else if (const toml::array* a = node.as_array()) {
    for (const toml::node& child : *a) reject_underflow(child, lines, source);
  } else if (node.is_floating_point() && node.as_floating_point()->get() == 0.0) {
    const toml::source_position at = node.source().begin;
    if (at.line == 0 || at.line > lines.size() || at.column == 0 ||
        at.column > lines[at.line - 1].size())
      return;
    const std::string_view line = lines[at.line - 1].substr(at.column - 1);
    const std::string token(line.substr(0, line.find_first_of(" \t,]}#")));
    if (underflows(token))
      throw InputError(source + ":" + std::to_string(at.line) + ": " + token + ": " + kUnderflow);
  }
}

toml::table parse_checked(const std::string& text, const std::string& source) {
  reject_invalid_utf8(text, source);
  const std::string ascii = ascii_for_toml(text, source);
  toml::table table = toml::parse(ascii, source);
  std::vector<std::string_view> lines;
  for (std::size_t begin = 0; begin <= ascii.size();) {
    const std::size_t end = std::min(ascii.find('\n', begin), ascii.size());
    lines.push_back(std::string_view(ascii).substr(begin, end - begin));
    begin = end + 1;
  }
  reject_underflow(table, lines, source);
  return table;
}

}  // namespace

toml::table parsed_value(const std::string& value, const std::string& source) {
  return parse_checked("v = " + value, source);
}

void Params::merge_toml_text(const std::string& text, const std::string& source) {
  try {
    merge_layer(merged_, origin_, parse_checked(text, source), {source, "", ++layers_}, false);
  } catch (const toml::parse_error& e) {
    throw InputError(source + ":" + std::to_string(e.source().begin.line) + ": " +
                     std::string(e.description()));
  }
}

std::string read_run_file(const std::string& path) {
  if (unsafe_input_file(path))
    throw InputError(path + ": the run file is not a regular file (a directory, FIFO or device)");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(path + ": cannot open the run file for reading");
  // Read to a bound (a pipe has no size to look at first).
  constexpr std::size_t kMaxRunFile = 16u << 20;
  std::string text;
  std::array<char, 1 << 16> block;
  while (in.read(block.data(), block.size()) || in.gcount() > 0) {
    text.append(block.data(), static_cast<std::size_t>(in.gcount()));
    if (text.size() > kMaxRunFile)
      throw InputError(
          path +
          ": the run file is over 16 MiB (a run file is a few kB; is this the packing file?)");
  }
  if (in.bad()) throw InputError(path + ": read error");
  if (text.starts_with("\xEF\xBB\xBF")) text.erase(0, 3);  // a UTF-8 byte-order mark (some editors)
  return text;
}

void Params::merge_toml_file(const std::string& path, const std::string* bytes) {
  const std::string text = bytes ? *bytes : read_run_file(path);
  toml::table layer;
  try {
    layer = parse_checked(text, path);
  } catch (const toml::parse_error& e) {
    throw InputError(path + ":" + std::to_string(e.source().begin.line) + ": " +
                     std::string(e.description()));
  }
  if (layer.empty()) empty_file_ = path;
  merge_layer(merged_, origin_, layer, {path, path, ++layers_}, true);
}

std::string trimmed(const std::string& s) {
  const auto first = s.find_first_not_of(" \t"), last = s.find_last_not_of(" \t");
  return first == std::string::npos ? "" : s.substr(first, last - first + 1);
}

std::string assignment_key(const std::string& key_equals_value) {
  return trimmed(key_equals_value.substr(0, key_equals_value.find('=')));
}

namespace {

// A --set value the user wrote as TOML: a quoted string, an inline table (`{` with a `=` or a
// closing `}`) or an array (`[...]`). Anything else that does not parse is a bare word, a string:
// `[x].xyz` is a file name.
bool written_as_toml(const std::string& value) {
  if (value.empty()) return false;
  const char first = value.front(), last = value.back();
  return first == '"' || first == '\'' ||
         (first == '{' && (last == '}' || value.find('=') != std::string::npos)) ||
         (first == '[' && last == ']');
}

// Where in a --set's `value` TOML failed ("v = " came before it), and why; inside a table or an
// array a text is a string only in quotes.
std::string not_toml(const toml::parse_error& e, const std::string& value) {
  constexpr std::size_t kPrefix = 4;  // "v = "
  const std::size_t column = e.source().begin.column;
  const std::size_t at = column > kPrefix ? std::min(column - kPrefix - 1, value.size()) : 0;
  // Non-ASCII characters reach the parser as \uXXXX escapes: its column is not the value's.
  const bool ascii = std::all_of(value.begin(), value.end(),
                                 [](char c) { return static_cast<unsigned char>(c) < 0x80; });
  const std::string where = !ascii               ? "in it"
                            : at >= value.size() ? "at its end"
                                                 : "at character " + std::to_string(at + 1) +
                                                       " (`" + value.substr(at) + "`)";
  const std::string hint =
      value.front() == '{'   ? "; a table is {key = value, ...}, a text in it quoted: "
                               "{file = \"p.xyz\"}"
      : value.front() == '[' ? "; an array is [value, ...], a text in it quoted: [\"a\", \"b\"]"
                             : "";
  return std::string(e.description()) + ", " + where + hint;
}

}  // namespace

void Params::merge_assignment(const std::string& key_equals_value, const std::string& origin,
                              bool swept) {
  const std::string named = origin.empty() ? "--set " + key_equals_value : origin;
  const auto eq = key_equals_value.find('=');
  const std::string key = assignment_key(key_equals_value);
  const auto parts = split_key(key);
  if (eq == std::string::npos || parts.empty() || key.back() == '.' ||
      std::any_of(parts.begin(), parts.end(), [](const std::string& part) { return part.empty(); }))
    throw InputError(named + ": expected KEY=VALUE with KEY like material.conductivity");
  const std::string value = trimmed(key_equals_value.substr(eq + 1));
  if (underflows(value)) throw InputError(named + ": `" + key + "` = " + value + ": " + kUnderflow);
  toml::table parsed;
  try {
    parsed = parsed_value(value, "--set");
  } catch (const toml::parse_error& e) {
    // A table, an array or a quoted string is TOML the user wrote: its error is theirs to mend,
    // not a bare word (`{conductivity=abc}` was taken as text, then told to be a table).
    if (written_as_toml(value))
      throw InputError(named + ": the value of `" + key + "` is not TOML: " + not_toml(e, value));
    parsed = toml::table{{"v", value}};    // a bare word: a string
  } catch (const std::runtime_error& e) {  // non-ASCII outside quotes, a number below a double's
    if (written_as_toml(value)) throw InputError(named + ": " + e.what());
    parsed = toml::table{{"v", value}};
  }
  if (parsed.size() != 1)  // "5\nbogus = 7": the second line would go unread
    throw InputError(named + ": the value of `" + key + "` must be one TOML value (" +
                     std::to_string(parsed.size()) + " assignments found: a line break?)");
  // A table given whole replaces what was typed for the keys under it.
  std::erase_if(raw_values_, [&](const auto& kv) { return kv.first.starts_with(key + "."); });
  raw_values_[key] = value;
  merge_value(merged_, origin_, key, *parsed.get("v"), {named, "", ++layers_, true, swept}, false,
              named);
}

const toml::node* Params::find(const std::string& key) const {
  return merged_.at_path(key).node();
}

bool Params::has(const std::string& key) const {
  return find(key) != nullptr;
}

// A key's own layer, or for a key given as a table (`conductivity = {a = 1}`) the earliest layer
// of its entries: the one that made it a table (set_origin keeps only the layers whose values are
// in the merged table).
const KeyOrigin* Params::origin(const std::string& key) const {
  if (const auto it = origin_.find(key); it != origin_.end()) return &it->second;
  const std::string below = key + ".";
  const KeyOrigin* first = nullptr;
  for (auto it = origin_.lower_bound(below); it != origin_.end() && it->first.starts_with(below);
       ++it)
    if (!first || it->second.layer < first->layer) first = &it->second;
  // A table sets its keys one by one (merge_value), so a key under one has its own origin; an
  // empty table is the origin of no key under it (`--set 'thermal={}'` set no wall temperature).
  return first;
}

std::string Params::where(const std::string& key) const {
  const KeyOrigin* o = origin(key);
  return o ? o->at + ": " : "";
}

bool Params::set_later(const std::string& later, const std::string& earlier) const {
  const KeyOrigin *a = origin(later), *b = origin(earlier);
  return a && b && a->layer > b->layer && !b->command_line;
}

std::string Params::source_of(const std::string& key) const {
  const KeyOrigin* o = origin(key);
  return o ? o->at : "the default";
}

bool Params::set_on_command_line(const std::string& key) const {
  const KeyOrigin* o = origin(key);
  return o && o->command_line;
}

bool Params::swept(const std::string& key) const {
  const KeyOrigin* o = origin(key);
  return o && o->swept;
}

bool Params::set_in_run_file(const std::string& key) const {
  const KeyOrigin* o = origin(key);
  return o && !o->file.empty();
}

bool Params::differs_from_default(const std::string& key) const {
  const auto fallback = number_defaults_.find(key);
  const toml::node* node = resolved_.at_path(key).node();
  if (fallback == number_defaults_.end() || !node) return true;
  if (const auto* v = node->as_floating_point()) return v->get() != fallback->second;
  if (const auto* i = node->as_integer()) return double(i->get()) != fallback->second;
  if (const auto* b = node->as_boolean()) return (b->get() ? 1.0 : 0.0) != fallback->second;
  return true;
}

std::string Params::shown(const std::string& key) const {
  const toml::node* node = resolved_.at_path(key).node();
  if (!node) return "";
  if (const auto* v = node->as_floating_point()) return shown_number(v->get());
  if (const auto* w = node->as_string()) return "\"" + w->get() + "\"";
  return repr(*node);
}

void Params::forget(const std::string& key) {
  const auto parts = split_key(key);
  toml::table* t = &merged_;
  for (std::size_t k = 0; t && k + 1 < parts.size(); ++k) t = t->get_as<toml::table>(parts[k]);
  if (t) t->erase(parts.back());
  origin_.erase(key);
}

std::string Params::path(const std::string& key) {
  const std::string v = text(key, "");
  const KeyOrigin* o = origin(key);
  if (v.empty() || std::filesystem::path(v).is_absolute()) return v;
  // Absolute in the resolved run file: `config` output and a checkpoint work from anywhere. From
  // the run file's folder, unless the run file is a pipe or a descriptor (`run <(...)`, whose
  // folder is /dev/fd; `run /dev/stdin < run.toml`), when it is read from the working directory,
  // as a `--set` is.
  std::error_code ec;
  const std::string& file = o ? o->file : std::string();
  const bool descriptor = file.starts_with("/dev/") || file.starts_with("/proc/");
  const bool in_a_folder =
      !file.empty() && !descriptor && std::filesystem::is_regular_file(file, ec);
  const std::filesystem::path folder =
      in_a_folder ? std::filesystem::path(file).parent_path() : std::filesystem::path();
  const std::string resolved = std::filesystem::absolute(folder / v).lexically_normal().string();
  // The run file's folder may be named in any bytes; config, checkpoints and summary.json hold
  // the path as UTF-8 text (a summary of such a path failed at the run's end, losing the run).
  if (first_invalid_utf8(resolved) != std::string_view::npos)
    fail(key, bytes_shown(resolved),
         "the path is not valid UTF-8 (run files, config and summary.json hold it as UTF-8 "
         "text); rename the file or the folders on its path");
  record(key, toml::value<std::string>(resolved));
  return resolved;
}

std::map<std::string, std::string> Params::origins() const {
  std::map<std::string, std::string> at;
  for (const auto& [key, o] : origin_) at[key] = o.at;
  return at;
}

void Params::record(const std::string& key, toml::node&& value) {
  used_.insert(key);
  set_path(resolved_, key, value);
}

void Params::fail(const std::string& key, const std::string& value,
                  const std::string& limit) const {
  throw InputError(where(key) + "`" + key + "` = " + value + ": " + limit);
}

double Params::number(const std::string& key, double fallback, double lo, double hi, bool lo_open,
                      bool hi_open, double stated_hi) {
  // ">= 0 and <= 1e+20": every refusal names the range (a NaN or a word was told only "must be
  // finite" or "must be a number", contract review).
  std::string range = std::string(lo_open ? "> " : ">= ") + shown_number(lo);
  if (hi < std::numeric_limits<double>::max())
    range += (hi_open ? " and < " : " and <= ") + shown_number(hi);
  else if (stated_hi < std::numeric_limits<double>::max())
    range += " and <= " + shown_number(stated_hi);
  const toml::node* node = find(key);
  const double v = node ? number_value(key, *node, range) : fallback;
  const bool below = lo_open ? !(v > lo) : !(v >= lo);
  const bool above = hi_open ? !(v < hi) : !(v <= hi);
  if (below || above) fail(key, shown_number(v), "must be " + range);
  record(key, toml::value<double>(v));
  number_defaults_[key] = fallback;
  return v;
}

double Params::number_value(const std::string& key, const toml::node& node,
                            const std::string& range) const {
  double v = 0;
  if (node.is_integer()) v = double(node.as_integer()->get());
  else if (node.is_floating_point()) v = node.as_floating_point()->get();
  else if (node.is_string() && beyond_doubles(node.as_string()->get()) > 0)
    fail(key, repr(node), "must be a finite number " + range + " (it is beyond a double's)");
  else fail(key, repr(node), "must be a number " + range);
  if (!std::isfinite(v)) fail(key, repr(node), "must be a finite number " + range);
  return v;
}

double Params::number_or(const std::string& key, double fallback, double lo, double stated_hi,
                         double special, const std::string& meaning) {
  const std::string rule = ">= " + shown_number(lo) + " and <= " + shown_number(stated_hi) +
                           ", or " + shown_number(special) + " (" + meaning + ")";
  const toml::node* node = find(key);
  const double v = node ? number_value(key, *node, rule) : fallback;
  if (v != special && !(v >= lo)) fail(key, shown_number(v), "must be " + rule);
  record(key, toml::value<double>(v));
  number_defaults_[key] = fallback;
  return v;
}

namespace {

// A whole number written as a float (1e3, 1000.0) is a float to TOML: say how to write it.
std::string written_as_integer_hint(const toml::node& node) {
  const auto* f = node.as_floating_point();
  if (!f || !std::isfinite(f->get()) || f->get() != std::trunc(f->get())) return "";
  return ", written without a decimal point or exponent (TOML reads 1e3 and 1000.0 as floats)";
}

}  // namespace

std::int64_t Params::integer(const std::string& key, std::int64_t fallback, std::int64_t lo,
                             std::int64_t hi) {
  std::int64_t v = fallback;
  if (const toml::node* node = find(key)) {
    if (!node->is_integer())
      fail(key, repr(*node),
           "must be an integer >= " + std::to_string(lo) + " and <= " + std::to_string(hi) +
               written_as_integer_hint(*node));
    v = node->as_integer()->get();
  }
  if (v < lo || v > hi)
    fail(key, std::to_string(v),
         "must be >= " + std::to_string(lo) + " and <= " + std::to_string(hi));
  record(key, toml::value<std::int64_t>(v));
  number_defaults_[key] = double(fallback);
  return v;
}

// A name TOML reads as a number, a boolean or a date (a file named 123) is a string in quotes:
// how to write it where it was given.
std::string Params::quoting_hint(const std::string& key, const toml::node& node) const {
  if (node.is_table() || node.is_array()) return "";
  // As the user wrote it on the command line (TOML prints 1e3 back as 1000.0, another name).
  const auto raw = raw_values_.find(key);
  const std::string written =
      set_on_command_line(key) && raw != raw_values_.end() ? raw->second : repr(node);
  return " (TOML reads " + written + " as a " +
         std::string(node.is_number()    ? "number"
                     : node.is_boolean() ? "boolean"
                                         : "date or time") +
         ": a name is written in quotes, \"" + written + "\"" +
         (set_on_command_line(key) && !swept(key) ? ": --set '" + key + "=\"" + written + "\"'"
                                                  : std::string()) +
         ")";
}

std::string Params::text(const std::string& key, const std::string& fallback) {
  std::string v = fallback;
  if (const toml::node* node = find(key)) {
    if (!node->is_string()) fail(key, repr(*node), "must be a string" + quoting_hint(key, *node));
    v = node->as_string()->get();
  }
  record(key, toml::value<std::string>(v));
  return v;
}

std::string Params::choice(const std::string& key, const std::string& fallback,
                           std::initializer_list<const char*> allowed) {
  const std::string v = text(key, fallback);
  for (const char* a : allowed)
    if (v == a) return v;
  std::string list;
  for (const char* a : allowed) list += (list.empty() ? "" : ", ") + std::string(a);
  fail(key, "\"" + v + "\"", "must be one of " + list);
}

bool Params::flag(const std::string& key, bool fallback) {
  bool v = fallback;
  if (const toml::node* node = find(key)) {
    if (!node->is_boolean()) fail(key, repr(*node), "must be true or false");
    v = node->as_boolean()->get();
  }
  record(key, toml::value<bool>(v));
  number_defaults_[key] = fallback ? 1.0 : 0.0;
  return v;
}

std::string Params::number_or_word(const std::string& key, double& value, double lo, double hi,
                                   std::initializer_list<const char*> words,
                                   const std::string& fallback_word, const std::string& unit,
                                   bool lo_open, double stated_hi) {
  const toml::node* node = find(key);
  std::string list;
  for (const char* a : words) list += std::string(" or \"") + a + "\"";
  // A string beyond a double's range ('1e400') is a number to refuse as one, not a word.
  if (!node || (node->is_string() && beyond_doubles(node->as_string()->get()) == 0)) {
    const std::string w = node ? std::string(node->as_string()->get()) : fallback_word;
    for (const char* a : words)
      if (w == a) {
        record(key, toml::value<std::string>(w));
        return w;
      }
    fail(key, "\"" + w + "\"", "must be a number in " + unit + list);
  }
  // true, a table: name the words too (a string here is one beyond a double's range)
  if (!node->is_integer() && !node->is_floating_point() && !node->is_string())
    fail(key, repr(*node), "must be a number in " + unit + list);
  try {
    value = number(key, 0.0, lo, hi, lo_open, false, stated_hi);
  } catch (const InputError& e) {  // out of range or not finite: the words are still choices
    throw InputError(std::string(e.what()) + " (in " + unit + ")" + list);
  }
  number_defaults_.erase(key);  // its default is the word: any number differs from it
  return "";
}

std::size_t edit_distance(const std::string& a, const std::string& b) {
  std::vector<std::size_t> row(b.size() + 1);
  for (std::size_t j = 0; j <= b.size(); ++j) row[j] = j;
  for (std::size_t i = 1; i <= a.size(); ++i) {
    std::size_t diag = row[0];
    row[0] = i;
    for (std::size_t j = 1; j <= b.size(); ++j) {
      const std::size_t up = row[j];
      row[j] = std::min({row[j] + 1, row[j - 1] + 1, diag + (a[i - 1] != b[j - 1])});
      diag = up;
    }
  }
  return row[b.size()];
}

namespace {

// The part of a dotted key after its last dot: "conductivity" of "material.conductivity".
std::string leaf_of(const std::string& key) {
  const std::size_t dot = key.rfind('.');
  return dot == std::string::npos ? key : key.substr(dot + 1);
}

// " (did you mean `a`, `b` or `c`?)", or "" when `keys` is empty or too many to offer.
std::string offered(const std::vector<std::string>& keys) {
  if (keys.empty() || keys.size() > 4) return "";
  std::string text = " (did you mean ";
  for (std::size_t k = 0; k < keys.size(); ++k)
    text += (k == 0 ? "" : k + 1 == keys.size() ? " or " : ", ") + ("`" + keys[k] + "`");
  return text + "?)";
}

// What an unknown key may have meant. A key cut short that begins several (`beam.direction`):
// all of them (spelling offered `beam.direction_x` alone). Else did_you_mean's spelling. Else a
// key in the wrong table or none (`thermal.conductivity`, `conductivity`, or a commented key
// uncommented under the last table of a file, `thermal.beam.gaussian_width`): the known keys of
// the same last name; else the one key it begins (`beam.diameter`).
std::string key_elsewhere(const std::string& typed, const std::set<std::string>& known) {
  std::vector<std::string> same_leaf, longer;
  for (const std::string& key : known) {
    if (leaf_of(key) == leaf_of(typed)) same_leaf.push_back(key);
    else if (typed.size() >= 4 && key.starts_with(typed)) longer.push_back(key);
  }
  if (longer.size() >= 2) return offered(longer);
  if (std::string near = did_you_mean(typed, known); !near.empty()) return near;
  return offered(same_leaf.empty() ? longer : same_leaf);
}

}  // namespace

void Params::check_all_used() const {
  for (const std::string& key : leaf_keys(merged_)) {
    if (used_.count(key)) continue;
    // `[[beam]]` (an array of tables) or `beam = [...]`: a table's name given as something else.
    const auto member = std::find_if(used_.begin(), used_.end(), [&](const std::string& known) {
      return known.size() > key.size() && known.compare(0, key.size() + 1, key + ".") == 0;
    });
    if (member != used_.end() && find(key)->is_table()) continue;  // `[beam]`, keys all left out
    if (member != used_.end())
      throw InputError(where(key) + "`" + key + "` is a table of keys (`" + *member +
                       "`, ...): write it once as [" + key + "], not as [[" + key +
                       "]] or a value");
    throw InputError(where(key) + "unknown key `" + key + "`" + key_elsewhere(key, used_));
  }
}

}  // namespace beampack::tools
