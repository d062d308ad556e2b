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

#include "tests/expect_error.h"
#include "tests/test_dirs.h"
#include "tools/svg_plot.h"

namespace fs = std::filesystem;

namespace beampack::tools {
namespace {

// The text of every <text> element whose attributes contain `attribute`, in order: `y="380"`
// picks the (first panel's) x axis tick labels, `x="8"` the y axis's.
std::vector<std::string> svg_texts(const std::string& svg, const std::string& attribute = "") {
  std::vector<std::string> out;
  const std::regex text("<text[^>]*" + attribute + "[^>]*>([^<]*)</text>");
  for (auto it = std::sregex_iterator(svg.begin(), svg.end(), text); it != std::sregex_iterator();
       ++it)
    out.push_back((*it)[1]);
  return out;
}

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
