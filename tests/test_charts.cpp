// sweep.svg and convergence.svg: their axes, their text as XML, and what sweep and converge
// refuse, skip and say.
#include <gtest/gtest.h>

#include <sys/wait.h>

#include <algorithm>
#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <regex>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include "tests/cli_runner.h"
#include "tests/expect_error.h"
#include "tests/svg_texts.h"
#include "tests/test_dirs.h"
#include "tools/svg_plot.h"

namespace fs = std::filesystem;

namespace beampack::tools {
namespace {

using beampack::testing::svg_texts;

std::vector<std::string> x_labels(const std::string& svg) {
  return svg_texts(svg, "y=\"380\"");
}

bool all_distinct(const std::vector<std::string>& labels) {
  return std::set<std::string>(labels.begin(), labels.end()).size() == labels.size();
}

// The cy of every circle, in order.
std::vector<double> circle_ys(const std::string& svg) {
  std::vector<double> out;
  const std::regex circle("<circle cx=\"[^\"]*\" cy=\"([^\"]*)\"");
  for (auto it = std::sregex_iterator(svg.begin(), svg.end(), circle); it != std::sregex_iterator();
       ++it)
    out.push_back(std::stod((*it)[1]));
  return out;
}

// The x tick labels on the row at `y` (the first panel's: 380, a second row 394), each with its
// centre: (x, text).
std::vector<std::pair<double, std::string>> placed_x_labels(const std::string& svg, int y = 380) {
  std::vector<std::pair<double, std::string>> out;
  const std::regex text("<text x=\"([^\"]*)\" y=\"" + std::to_string(y) + "\"[^>]*>([^<]*)</text>");
  for (auto it = std::sregex_iterator(svg.begin(), svg.end(), text); it != std::sregex_iterator();
       ++it)
    out.emplace_back(std::stod((*it)[1]), (*it)[2]);
  return out;
}

// Neighbouring labels on a row do not overprint (at 7 px a character, font-size 12), and each
// lies within the chart's 640 px.
void expect_apart_and_within(const std::vector<std::pair<double, std::string>>& labels) {
  for (std::size_t k = 0; k < labels.size(); ++k) {
    const double half = 3.5 * double(labels[k].second.size());
    EXPECT_GE(labels[k].first - half, 0.0) << labels[k].second;
    EXPECT_LE(labels[k].first + half, 640.0) << labels[k].second;
    if (k == 0) continue;
    EXPECT_GT(labels[k].first - labels[k - 1].first,
              half + 3.5 * double(labels[k - 1].second.size()))
        << labels[k - 1].second << " and " << labels[k].second;
  }
}

// Neighbouring x labels do not overprint, however many digits tell the ticks apart: 13-digit
// labels 73 px apart did (a user audit's sweep of sample.size over 0.001 and 0.0010000001); numbers
// are then on every second tick, and a short axis keeps them all. A category's label is its
// point's only name: every one is kept, distinct, on two rows and shortened around "..." when
// long, and within the chart (the first was centred on the frame's edge, half off the image).
TEST(Charts, NeighbouringTickLabelsDoNotOverprint) {
  const Chart fine{"t", "x", "y", false, false, {{"a", {0.001, 0.0010000001}, {1, 2}}}};
  const auto numbers = placed_x_labels(render_svg(fine));
  ASSERT_GE(numbers.size(), 2u) << render_svg(fine);
  expect_apart_and_within(numbers);
  const Chart plain{"t", "x", "y", false, false, {{"a", {0, 1, 2, 3, 4, 5}, {1, 2, 3, 4, 5, 6}}}};
  EXPECT_EQ(placed_x_labels(render_svg(plain)).size(), 6u) << render_svg(plain);
  const std::vector<std::string> names = {"a-long-packing-file-name.xyz",
                                          "another-packing.xyz",
                                          "b.xyz",
                                          "c.xyz",
                                          "the-last-packing-file.xyz",
                                          "f.xyz",
                                          "g.xyz"};
  const Chart words{
      "t", "x", "y", false, false, {{"a", {0, 1, 2, 3, 4, 5, 6}, {1, 2, 3, 4, 5, 6, 7}}}, names};
  const std::string svg = render_svg(words);
  const auto first = placed_x_labels(svg, 380), second = placed_x_labels(svg, 394);
  expect_apart_and_within(first);
  expect_apart_and_within(second);
  std::set<std::string> shown;
  for (const auto& row : {first, second})
    for (const auto& [x, label] : row) shown.insert(label);
  EXPECT_EQ(shown.size(), names.size()) << svg;  // each point named, no two alike
  EXPECT_TRUE(shown.count("b.xyz")) << svg;      // a short name whole
  EXPECT_TRUE(std::any_of(shown.begin(), shown.end(), [](const std::string& l) {
    return l.starts_with("a-lo") && l.find("...") != std::string::npos && l.ends_with("xyz");
  })) << svg;
}

// Tick labels below 1e-12 all read "0" (an absolute round-off threshold): pulse durations of
// 1e-13..1e-12 s were labelled 0 0 0 0 0 1e-12, time steps of 1e-14..1e-13 s all 0.
TEST(Charts, TickLabelsOfTinyValuesAreTheirValues) {
  const Chart durations{"t",   "x",   "y",
                        false, false, {{"a", {1e-13, 2e-13, 4e-13, 1e-12}, {1, 2, 3, 4}}}};
  const std::vector<std::string> d = x_labels(render_svg(durations));
  ASSERT_GE(d.size(), 4u);
  EXPECT_TRUE(all_distinct(d)) << ::testing::PrintToString(d);
  EXPECT_NE(std::find(d.begin(), d.end(), "2e-13"), d.end()) << ::testing::PrintToString(d);
  const Chart steps{"t", "x", "y", false, false, {{"a", {1e-14, 3e-14, 1e-13}, {1, 2, 3}}}};
  const std::vector<std::string> s = x_labels(render_svg(steps));
  ASSERT_GE(s.size(), 3u);
  EXPECT_TRUE(all_distinct(s)) << ::testing::PrintToString(s);
  EXPECT_EQ(std::count(s.begin(), s.end(), "0"), std::ptrdiff_t(s.front() == "0"));
  // A tick on 0 itself, reached by adding steps, is still 0, not 1e-29.
  const Chart through_zero{"t", "x", "y", false, false, {{"a", {-0.3, 0.7}, {1, 2}}}};
  const std::vector<std::string> z = x_labels(render_svg(through_zero));
  EXPECT_NE(std::find(z.begin(), z.end(), "0"), z.end()) << ::testing::PrintToString(z);
}

// Values far from 0 and close together: the axis no longer starts at 0 (1000..1002 sat in its last
// 0.2%), and the labels have the digits that tell neighbouring ticks apart.
TEST(Charts, AxisOfCloseValuesAwayFromZeroDoesNotStartAtZero) {
  const Chart close{"t", "x", "y", false, false, {{"a", {1000, 1001, 1002}, {1, 2, 3}}}};
  const std::vector<std::string> labels = x_labels(render_svg(close));
  ASSERT_GE(labels.size(), 3u);
  EXPECT_TRUE(all_distinct(labels)) << ::testing::PrintToString(labels);
  EXPECT_NE(labels.front(), "0");
  EXPECT_GE(std::stod(labels.front()), 990.0) << ::testing::PrintToString(labels);
  // Values that fill most of the axis from 0 keep it (the paper's K from 0 to 400).
  const Chart k{"t", "x", "y", false, false, {{"a", {0, 100, 400}, {1, 2, 3}}}};
  EXPECT_EQ(x_labels(render_svg(k)).front(), "0");
}

// Errors of exactly 0 on a log axis: in a band of their own below it, labelled 0 beside the band
// (not on a tick), not on the axis's lower edge where they read as its lowest tick.
TEST(Charts, ZerosOnALogAxisAreDrawnInABandOfTheirOwn) {
  const Chart chart{"t", "x", "y", true, true, {{"a", {0.5, 2.0, 12.0}, {3e-5, 0.2, 0.0}}}};
  const std::string svg = render_svg(chart);
  const std::vector<std::string> y = svg_texts(svg, "x=\"8\"");
  ASSERT_EQ(y.size(), 7u) << svg;  // 1e-5 .. 1e0, and the band's 0
  EXPECT_EQ(y.back(), "0");
  EXPECT_CONTAINS(svg, "stroke-dasharray");  // the band
  const std::vector<double> cy = circle_ys(svg);
  ASSERT_EQ(cy.size(), 3u);
  // The lowest tick, 1e-5, is the frame's lower edge; the zero lies below it, the 3e-5 above.
  const std::regex frame("<rect x=\"80\" y=\"40\" width=\"[^\"]*\" height=\"([^\"]*)\"");
  std::smatch m;
  ASSERT_TRUE(std::regex_search(svg, m, frame)) << svg;
  const double lower_edge = 40 + std::stod(m[1]);
  EXPECT_LT(cy[0], lower_edge);
  EXPECT_GT(cy[2], lower_edge + 5) << svg;
  // The line does not run into the band: it joins the two values on the axis only.
  EXPECT_EQ(std::count(svg.begin(), svg.end(), 'L'), 1) << svg;
}

// Every error 0: the log axis has no value to fit. It showed 1e0..1e1 with every point on 1e0
// (a 100% error); now it has no ticks, and says that every value is 0.
TEST(Charts, ALogAxisOfZerosOnlySaysSo) {
  const Chart chart{"t", "x", "y", true, true, {{"a", {0.5, 2.0}, {0.0, 0.0}}}};
  const std::string svg = render_svg(chart);
  EXPECT_EQ(svg_texts(svg, "x=\"8\""), std::vector<std::string>{"0"}) << svg;
  EXPECT_CONTAINS(svg, "every value is 0");
}

// XML 1.0 has no way to write a control character but tab and line breaks, nor bytes that are
// not UTF-8: a swept file name `c\x01.xyz` made sweep.svg malformed.
TEST(Charts, TextThatXmlForbidsIsWrittenAsHex) {
  EXPECT_EQ(xml_text("c\x01.xyz"), "c\\x01.xyz");
  EXPECT_EQ(xml_text("a&b<c>d"), "a&amp;b&lt;c&gt;d");
  EXPECT_EQ(xml_text("caf\xC3\xA9"), "caf\xC3\xA9");            // UTF-8 é kept
  EXPECT_EQ(xml_text("caf\xE9.xyz"), "caf\\xE9.xyz");           // Latin-1 é is no UTF-8
  EXPECT_EQ(xml_text("\xC0\xAF"), "\\xC0\\xAF");                // an overlong '/'
  EXPECT_EQ(xml_text("\xED\xA0\x80"), "\\xED\\xA0\\x80");       // a surrogate
  EXPECT_EQ(xml_text("\xEF\xBF\xBF"), "\\xEF\\xBF\\xBF");       // U+FFFF
  EXPECT_EQ(xml_text("\xF0\x9F\x98\x80"), "\xF0\x9F\x98\x80");  // U+1F600 kept
  EXPECT_EQ(xml_text("a\tb\x1F"), "a\tb\\x1F");
  const Chart chart{"t\x02",          "x\x7F", "y", false, false, {{"s\x1B", {0, 1}, {1, 2}}},
                    {"c\x01", "\xFF"}};
  const std::string svg = render_svg(chart);
  for (const char c : svg)
    EXPECT_FALSE(static_cast<unsigned char>(c) < 0x20 && c != '\n') << int(c);
  EXPECT_NOT_CONTAINS(svg, "\xFF");
  EXPECT_CONTAINS(svg, ">c\\x01<");
}

// Panels stack, each with its own axes: convergence.svg's two.
TEST(Charts, PanelsStackOneBelowTheOther) {
  const Chart a{"first", "x", "y", true, true, {{"a", {1, 10}, {1e-3, 1e-2}}}};
  const Chart b{"second", "x", "y", true, true, {{"a", {1, 10}, {1, 20}}}, {}, "a note"};
  const std::string svg = render_svg(std::vector<Chart>{a, b});
  EXPECT_CONTAINS(svg, "height=\"840\"");
  EXPECT_CONTAINS(svg, "<g transform=\"translate(0,420)\">");
  EXPECT_CONTAINS(svg, ">second<");
  EXPECT_CONTAINS(svg, ">a note<");
}

}  // namespace
}  // namespace beampack::tools

// ---- The commands.

namespace {

using beampack::testing::fresh_dir;

using beampack::testing::file_text;
using beampack::testing::Result;
using beampack::testing::run;

std::string sweep_svg(const std::string& name, const std::string& args, Result* result = nullptr) {
  const fs::path out = fresh_dir(name);
  const Result r = run("sweep --preset quick --quiet " + args + " --out " + out.string());
  if (result) *result = r;
  EXPECT_EQ(r.code, 0) << r.output;
  return file_text(out / "sweep.svg");
}

// Values spanning two decades or more, all > 0: a log axis (optics.cutoff 1e-14..1e-10 crowded
// onto 0 on a linear one); fewer: linear.
TEST(ChartsCli, SweepsOverDecadesGetALogAxis) {
  const std::string svg =
      sweep_svg("sweep_log", "--param optics.cutoff --values 1e-14,1e-12,1e-10");
  EXPECT_EQ(beampack::tools::x_labels(svg),
            (std::vector<std::string>{"1e-14", "1e-13", "1e-12", "1e-11", "1e-10"}))
      << svg;
  EXPECT_CONTAINS(svg, "optics.cutoff (log scale)");
  const std::string linear =
      sweep_svg("sweep_linear", "--param material.conductivity --values 1,5,20");
  EXPECT_NOT_CONTAINS(linear, "log scale");
}

// The line follows the values' order on the axis: `--values 100,0,50` drew a zig-zag.
TEST(ChartsCli, SweepLineRunsInTheOrderOfTheAxis) {
  const std::string svg =
      sweep_svg("sweep_order", "--param material.conductivity --values 100,0,50");
  std::smatch m;
  ASSERT_TRUE(std::regex_search(svg, m, std::regex("<path d=\"M([^\"]*)\""))) << svg;
  std::vector<double> xs;
  const std::string d = m[1];
  const std::regex point("([0-9.e+-]+),[0-9.e+-]+");
  for (auto it = std::sregex_iterator(d.begin(), d.end(), point); it != std::sregex_iterator();
       ++it)
    xs.push_back(std::stod((*it)[1]));
  ASSERT_EQ(xs.size(), 3u) << d;
  EXPECT_TRUE(std::is_sorted(xs.begin(), xs.end())) << d;
}

// A value given twice, by any spelling the run reads as the same (1e2 is 100), is refused.
TEST(ChartsCli, SweepRefusesARepeatedValue) {
  const fs::path out = fresh_dir("sweep_repeat");
  const Result same =
      run("sweep --preset quick --quiet --param material.conductivity --values 1,1 --out " +
          out.string());
  EXPECT_EQ(same.code, 2) << same.output;
  EXPECT_CONTAINS(same.output, "--values: value 2 (1) repeats value 1 (1)");
  const Result spelt =
      run("sweep --preset quick --quiet --param material.conductivity --values 100,5,1e2 --out " +
          out.string());
  EXPECT_EQ(spelt.code, 2) << spelt.output;
  EXPECT_CONTAINS(spelt.output, "value 3 (1e2) repeats value 1 (100)");
  EXPECT_FALSE(fs::exists(out / "sweep.csv"));
}

// The sweep compared its values through a bare toml::parse, apart from the run files' checks:
// 1e-400 was the number 0 there ("repeats value 1 (0)") where the run refuses it as an
// underflow, and non-ASCII letters reached toml++ 3.3, which reaches undefined behaviour on
// such bytes between tokens (in Debian's shared library, where the sanitizers do not see it).
TEST(ChartsCli, SweepReadsItsValuesThroughTheRunFilesChecks) {
  const fs::path out = fresh_dir("sweep_non_ascii");
  const Result tiny =
      run("sweep --preset quick --quiet --param material.conductivity --values 0,1e-400 --out " +
          out.string());
  EXPECT_EQ(tiny.code, 2) << tiny.output;
  EXPECT_CONTAINS(tiny.output, "`material.conductivity` = 1e-400: underflows to 0");
  EXPECT_NOT_CONTAINS(tiny.output, "repeats");
  const Result word =
      run("sweep --preset quick --quiet --param beam.profile --values "
          "\"\xd0\x96\",flat --out " +
          out.string());
  EXPECT_EQ(word.code, 2) << word.output;
  EXPECT_CONTAINS(word.output, "`beam.profile` = \"\xd0\x96\": must be one of");
  const Result twice =
      run("sweep --preset quick --quiet --param beam.profile --values "
          "'\xc3\xa9,\"\xc3\xa9\"' --out " +
          out.string());
  EXPECT_EQ(twice.code, 2) << twice.output;
  EXPECT_CONTAINS(twice.output, "repeats value 1");
  EXPECT_FALSE(fs::exists(out / "sweep.csv"));
}

// TOML's 1_00 is the number 100 to the run, and now on the axis too (it was the word "1_00").
TEST(ChartsCli, SweepReadsValuesAsNumbersAsTheRunDoes) {
  const std::string svg =
      sweep_svg("sweep_toml", "--param material.conductivity --values 1_00,200,3_00");
  const std::vector<std::string> labels = beampack::tools::x_labels(svg);
  EXPECT_EQ(std::find(labels.begin(), labels.end(), "1_00"), labels.end())
      << ::testing::PrintToString(labels);
  EXPECT_NE(std::find(labels.begin(), labels.end(), "200"), labels.end())
      << ::testing::PrintToString(labels);
}

// `--param ' k'` ran k but wrote a csv header " k,...".
TEST(ChartsCli, SweepTrimsTheParamName) {
  const fs::path out = fresh_dir("sweep_trim");
  const Result r =
      run("sweep --preset quick --quiet --param ' material.conductivity ' --values 1,2 --out " +
          out.string());
  ASSERT_EQ(r.code, 0) << r.output;
  const std::string csv = file_text(out / "sweep.csv");
  EXPECT_EQ(csv.rfind("material.conductivity,", 0), 0u) << csv.substr(0, 40);
}

// `--set material.conductivity=3` was refused beside --param material.conductivity, but the same
// key set inside a table was taken, and --values overrode it without a word.
TEST(ChartsCli, SweepRefusesATableThatSetsTheSweptKey) {
  const fs::path out = fresh_dir("sweep_table");
  const Result r =
      run("sweep --preset quick --quiet --set 'material={conductivity=5}' --param "
          "material.conductivity --values 1,2 --out " +
          out.string());
  EXPECT_EQ(r.code, 2) << r.output;
  EXPECT_CONTAINS(r.output,
                  "--set material={conductivity=5}: sets `material.conductivity`, the "
                  "swept --param; its values come from --values");
  // A table of other keys is no conflict.
  const Result other =
      run("sweep --preset quick --quiet --set 'material={density=5000}' --param "
          "material.conductivity --values 1,2 --out " +
          out.string());
  EXPECT_EQ(other.code, 0) << other.output;
}

// A swept file name with a control character: sweep.svg stays well-formed XML, the name written
// with its hex.
TEST(ChartsCli, SweepChartOfAControlCharacterInAValueIsXml) {
  const fs::path out = fresh_dir("sweep_control");
  const std::string bed = "x y z r\n0.5e-3 0.5e-3 0.5e-3 1e-4\n0.5e-3 0.5e-3 0.82e-3 1.5e-4\n";
  const fs::path odd = out / "c\x01.xyz", plain = out / "b.xyz";
  std::ofstream(odd) << bed;
  std::ofstream(plain) << bed;
  const Result r =
      run("sweep --preset quick --quiet --set packing.source=file --param packing.file --values '" +
          odd.string() + "," + plain.string() + "' --out " + (out / "out").string());
  ASSERT_EQ(r.code, 0) << r.output;
  const std::string svg = file_text(out / "out" / "sweep.svg");
  EXPECT_CONTAINS(svg, "c\\x01.xyz");
  EXPECT_EQ(svg.find('\x01'), std::string::npos);
}

// converge's solver tolerance ladder, in a scene where no step solves iteratively (K = 0, the
// zohdi2013 preset's; or the direct solver): every rung would repeat its reference bit for bit,
// a ladder of errors of 0 that measured nothing. It is not run, and converge says so.
TEST(ChartsCli, ConvergeSkipsTheToleranceLadderWithoutAnIterativeSolve) {
  for (const std::string set :
       {"material.conductivity=0", "thermal.solver='\"direct\"'", "thermal.phi=0"}) {
    const fs::path out = fresh_dir("converge_no_solve");
    const Result r = run("converge --preset quick --quiet --set beam.rays=50 --set " + set +
                         " --out " + out.string());
    ASSERT_EQ(r.code, 0) << r.output;
    EXPECT_CONTAINS(r.output, "beampack: note: converge: the solver tolerance ladder is not run: ");
    EXPECT_CONTAINS(r.output, "so `thermal.tolerance` changes no result of this scene");
    const std::string csv = file_text(out / "convergence.csv");
    EXPECT_NOT_CONTAINS(csv, "solver tolerance");
    EXPECT_CONTAINS(csv, "rays per pulse");
    EXPECT_CONTAINS(file_text(out / "convergence.svg"), "solver tolerance ladder not run");
  }
}

// convergence.svg shows the temperature field's error too (up to 20 K here, where every error of
// v_v is 0 and was all the chart showed, on its "1e0" line).
TEST(ChartsCli, ConvergenceChartShowsTheTemperatureError) {
  const fs::path out = fresh_dir("converge_one_pulse");
  const Result r =
      run("converge --preset quick --quiet --set beam.rays=50 --set pulses.count=1 --out " +
          out.string());
  ASSERT_EQ(r.code, 0) << r.output;
  const std::string svg = file_text(out / "convergence.svg");
  EXPECT_CONTAINS(svg, "L2 error of T, K");
  EXPECT_CONTAINS(svg, "<g transform=\"translate(0,420)\">");
  const std::string lower = svg.substr(svg.find("translate(0,420)"));
  EXPECT_NOT_CONTAINS(lower, "every value is 0");
  EXPECT_GE(std::count(lower.begin(), lower.end(), 'L'), 3);  // lines on the log axes
}

// stdout is flushed before converge writes to stderr: through one pipe, a ladder's last line
// comes before the next ladder's warning (it came after it).
TEST(ChartsCli, ConvergeLinesAndWarningsKeepTheirOrderInOnePipe) {
  const fs::path out = fresh_dir("converge_order");
  const Result r =
      run("converge --preset quick --quiet --set beam.rays=50 --set pulses.count=0 --out " +
          out.string());
  ASSERT_EQ(r.code, 0) << r.output;
  const std::size_t line = r.output.find("time step          the reference");
  const std::size_t warning = r.output.find("the rays per pulse ladder's reference run absorbed");
  ASSERT_NE(line, std::string::npos) << r.output;
  ASSERT_NE(warning, std::string::npos) << r.output;
  EXPECT_LT(line, warning) << r.output;
}

}  // namespace
