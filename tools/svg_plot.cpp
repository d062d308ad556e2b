#include "tools/svg_plot.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <sstream>

namespace beampack::tools {
namespace {

constexpr double kWidth = 640, kHeight = 420, kLeft = 80, kRight = 160, kTop = 40, kBottom = 60;
// Below a log y axis, the band where values of exactly 0 are drawn: a log axis has no place for
// them, and on its lower edge they read as its lowest tick (a 100% error on convergence.svg).
constexpr double kZeroBand = 26, kZeroGap = 6;
const char* kColours[] = {"#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b"};

struct Axis {
  double lo = 0, hi = 1;
  bool log = false;
  bool empty = false;  // no value to place (a log axis of zeros only): no ticks
  double map(double v) const {
    const double a = log ? std::log10(v) : v;
    return (a - lo) / (hi - lo);
  }
};

enum class Zero { always, unless_crowded };

// The axis over the values (in log10 on a log axis; there values <= 0 have no place).
Axis fit_axis(const std::vector<double>& values, bool log, Zero zero) {
  double lo = std::numeric_limits<double>::infinity(), hi = -lo;
  for (double v : values) {
    if (!std::isfinite(v) || (log && v <= 0)) continue;
    const double a = log ? std::log10(v) : v;
    lo = std::min(lo, a);
    hi = std::max(hi, a);
  }
  const bool empty = !std::isfinite(lo);
  if (empty) lo = 0, hi = 1;
  if (log) lo = std::floor(lo), hi = std::ceil(hi);
  // One value: a span around it, not [v, v + 1]. Relative: 1e-13 and 2e-13 are two values.
  if (!(hi - lo > 1e-9 * std::max(std::abs(lo), std::abs(hi)))) {
    const double half = log || lo == 0 ? 1.0 : 0.5 * std::abs(lo);
    lo -= log ? 0.0 : half, hi += half;
  }
  if (!log) {  // a margin of 5% of the axis (of the values' span, it left 0.035 on the top edge
               // of an axis from 0 to 0.035)
    const bool from_zero = lo >= 0 && (zero == Zero::always || lo <= hi - lo);
    if (from_zero) lo = 0;
    const double pad = 0.05 * (hi - lo);
    lo = from_zero ? 0.0 : lo - pad;
    hi += pad;
  }
  return {lo, hi, log, empty};
}

// Tick step (in axis units: decades on a log axis): whole decades, or a 1-2-5 step, about five
// to a side.
double tick_step(const Axis& a) {
  const double span = a.hi - a.lo;
  if (a.log) return std::max(1.0, std::ceil(span / 6));
  const double decade = std::pow(10.0, std::floor(std::log10(span / 5)));
  double step = decade;
  for (double m : {2.0, 5.0, 10.0})
    if (span / step > 7) step = decade * m;
  return step;
}

// Tick positions; each label appears once.
std::vector<double> ticks(const Axis& a) {
  if (a.empty) return {};
  const double span = a.hi - a.lo, step = tick_step(a);
  std::vector<double> t;
  const double first = std::ceil(a.lo / step - 1e-9) * step;
  for (int k = 0; k < 20; ++k) {  // by index: a step below the values' last digit cannot stall
    const double v = first + k * step;
    if (v > a.hi + 1e-9 * span) break;
    if (t.empty() || v > t.back()) t.push_back(v);
  }
  return t;
}

// A tick's label. A tick within round-off of 0 is 0, judged against the step (1e-13 is no
// round-off on an axis of pulse durations; an absolute 1e-12 made every tick of one "0"); enough
// digits that neighbouring ticks differ (1000.5 beside 1000 on an axis from 1000 to 1002).
std::string tick_label(double a, const Axis& axis) {
  char buf[32];
  if (axis.log) {
    std::snprintf(buf, sizeof buf, "1e%d", int(std::lround(a)));
    return buf;
  }
  const double step = tick_step(axis);
  const double largest = std::max(std::abs(axis.lo), std::abs(axis.hi));
  const int digits = std::max(3, int(std::floor(std::log10(largest / step))) + 2);
  std::snprintf(buf, sizeof buf, "%.*g", digits, std::abs(a) < 1e-6 * step ? 0.0 : a);
  return buf;
}

// The length of the UTF-8 sequence at text[i] when it encodes a character XML 1.0 allows, else 0.
std::size_t xml_char_length(const std::string& text, std::size_t i) {
  const auto lead = static_cast<unsigned char>(text[i]);
  const std::size_t n = lead >= 0xC2 && lead <= 0xDF   ? 2
                        : lead >= 0xE0 && lead <= 0xEF ? 3
                        : lead >= 0xF0 && lead <= 0xF4 ? 4
                                                       : 0;
  if (n == 0 || i + n > text.size()) return 0;
  char32_t code = lead & (0x7F >> n);
  for (std::size_t k = 1; k < n; ++k) {
    const auto c = static_cast<unsigned char>(text[i + k]);
    if ((c & 0xC0) != 0x80) return 0;
    code = (code << 6) | (c & 0x3F);
  }
  const char32_t least = n == 2 ? 0x80 : n == 3 ? 0x800 : 0x10000;  // shorter forms are invalid
  const bool surrogate = code >= 0xD800 && code <= 0xDFFF;
  if (code < least || surrogate || code > 0x10FFFF || code == 0xFFFE || code == 0xFFFF) return 0;
  return n;
}

}  // namespace

// A swept file name `a&b.xyz` or `c<d.xyz` made the chart malformed, and so did `c\x01.xyz`
// (XML 1.0 has no escape for it, not even &#1;) and a file name that is not UTF-8.
std::string xml_text(const std::string& text) {
  std::string out;
  for (std::size_t i = 0; i < text.size();) {
    const auto c = static_cast<unsigned char>(text[i]);
    const std::size_t n = c < 0x80 ? 1 : xml_char_length(text, i);
    if (c == '&') out += "&amp;";
    else if (c == '<') out += "&lt;";
    else if (c == '>') out += "&gt;";
    else if (n == 0 || (c < 0x20 && c != '\t' && c != '\n' && c != '\r')) {
      char hex[8];
      std::snprintf(hex, sizeof hex, "\\x%02X", unsigned(c));
      out += hex;
    } else {
      out.append(text, i, n);
    }
    i += std::max<std::size_t>(n, 1);
  }
  return out;
}

namespace {

// Where a panel's plot sits: the frame of its axes, and below it, on a log y axis with values
// of 0, the band that holds them.
struct Frame {
  double w = kWidth - kLeft - kRight, h = kHeight - kTop - kBottom;  // h: frame and band
  double band = 0;                                                   // height of the 0 band
  double axis_h() const { return h - band; }
  double zero_y() const { return kTop + axis_h() + kZeroGap + 0.5 * (band - kZeroGap); }
};

bool has_zero_on_log_y(const Chart& chart) {
  if (!chart.log_y) return false;
  for (const Series& s : chart.series)
    for (double y : s.y)
      if (y == 0) return true;
  return false;
}

// About 7 px a character at font-size 12, and a 6 px gap between neighbouring labels.
constexpr double kCharWidth = 7, kLabelGap = 6;

// Every stride-th of `labels` (centred on ticks `spacing` px apart) so that none overprints its
// neighbour.
std::size_t label_stride(const std::vector<std::string>& labels, double spacing) {
  std::size_t widest = 0;
  for (const std::string& label : labels) widest = std::max(widest, label.size());
  if (!(spacing > 0)) return 1;
  return std::max<std::size_t>(
      1, std::size_t(std::ceil((kCharWidth * double(widest) + kLabelGap) / spacing)));
}

// `label` within `chars` characters: its start and end around "..." (sweep.csv has it whole).
std::string shortened(const std::string& label, std::size_t chars) {
  chars = std::max<std::size_t>(chars, 5);
  if (label.size() <= chars) return label;
  const std::size_t keep = chars - 3, head = (keep + 1) / 2;
  return label.substr(0, head) + "..." + label.substr(label.size() - (keep - head));
}

// A label's centre near x, moved in so that it stays within the chart's width.
double within_chart(double x, const std::string& label) {
  const double half = 0.5 * kCharWidth * double(label.size()) + 2;
  return std::clamp(x, half, std::max(half, kWidth - half));
}

// The x ticks, each label centred below its tick. Numbers too long for their ticks' spacing are
// put on every second (third, ...) tick, whose values are still told apart (13-digit labels 73 px
// apart overprinted each other). A category's label is its point's only name: every one is kept,
// on two rows when long, shortened around "..." when still too long.
void write_x_ticks(std::ostream& o, const Chart& chart, const Axis& ax, const Frame& f) {
  const bool categories = !chart.x_categories.empty();
  std::vector<double> x_ticks = ticks(ax);
  if (categories) {
    x_ticks.clear();
    for (std::size_t k = 0; k < chart.x_categories.size(); ++k) x_ticks.push_back(double(k));
  }
  std::vector<std::string> labels;
  for (double fx : x_ticks)
    labels.push_back(categories ? chart.x_categories[std::size_t(std::lround(fx))]
                                : tick_label(fx, ax));
  const auto at = [&](double fx) { return kLeft + f.w * (fx - ax.lo) / (ax.hi - ax.lo); };
  const double spacing = x_ticks.size() > 1 ? at(x_ticks[1]) - at(x_ticks[0]) : f.w;
  const std::size_t needed = label_stride(labels, spacing);  // for labels that do not overprint
  const std::size_t stride = categories ? 1 : needed, rows = categories && needed > 1 ? 2 : 1;
  const auto fits = std::size_t(std::max(0.0, (double(rows) * spacing - kLabelGap) / kCharWidth));
  for (std::size_t k = 0; k < x_ticks.size(); ++k) {
    const double x = at(x_ticks[k]);
    o << "<line x1=\"" << x << "\" y1=\"" << kTop + f.h << "\" x2=\"" << x << "\" y2=\""
      << kTop + f.h + 5 << "\" stroke=\"black\"/>";
    if (k % stride == 0) {
      const std::string label = categories ? shortened(labels[k], fits) : labels[k];
      o << "<text x=\"" << within_chart(x, label) << "\" y=\"" << kTop + f.h + 20 + 14 * (k % rows)
        << "\" text-anchor=\"middle\">" << xml_text(label) << "</text>";
    }
    o << "\n";
  }
}

// The y ticks, the 0 band (labelled 0 beside it, no tick: it is no place on the axis), and a
// note in the frame when a log axis has no value above 0 to place.
void write_y_ticks(std::ostream& o, const Axis& ay, const Frame& f) {
  for (double fy : ticks(ay)) {
    const double y = kTop + f.axis_h() * (1 - (fy - ay.lo) / (ay.hi - ay.lo));
    o << "<line x1=\"" << kLeft - 5 << "\" y1=\"" << y << "\" x2=\"" << kLeft << "\" y2=\"" << y
      << "\" stroke=\"black\"/>"
      << "<text x=\"" << 8 << "\" y=\"" << y + 4 << "\">" << xml_text(tick_label(fy, ay))
      << "</text>\n";
  }
  if (f.band > 0)
    o << "<rect x=\"" << kLeft << "\" y=\"" << kTop + f.axis_h() + kZeroGap << "\" width=\"" << f.w
      << "\" height=\"" << f.band - kZeroGap
      << "\" fill=\"#eeeeee\" stroke=\"black\" stroke-dasharray=\"4,3\"/>"
      << "<text x=\"" << 8 << "\" y=\"" << f.zero_y() + 4 << "\">0</text>\n";
  if (ay.empty)
    o << "<text x=\"" << kLeft + 10 << "\" y=\"" << kTop + f.axis_h() / 2 << "\">"
      << (f.band > 0 ? "every value is 0 (the band below)" : "no value above 0") << "</text>\n";
}

// The series: markers, and lines between neighbouring points on the axes (none into or out of
// the 0 band: the axis does not run on to it).
void write_series(std::ostream& o, const Chart& chart, const Axis& ax, const Axis& ay,
                  const Frame& f) {
  for (std::size_t k = 0; k < chart.series.size(); ++k) {
    const Series& s = chart.series[k];
    const char* colour = kColours[k % 6];
    std::ostringstream path;
    bool joined = false;  // the last point is on the axes: the next one joins it
    for (std::size_t i = 0; i < s.x.size(); ++i) {
      const bool placed = std::isfinite(s.y[i]) && !(chart.log_y && s.y[i] < 0) &&
                          !(chart.log_x && s.x[i] <= 0) && std::isfinite(s.x[i]);
      const bool zero = placed && chart.log_y && s.y[i] == 0;
      if (!placed || zero) joined = false;
      if (!placed) continue;
      const double x = kLeft + f.w * ax.map(s.x[i]);
      const double y = zero ? f.zero_y() : kTop + f.axis_h() * (1 - ay.map(s.y[i]));
      if (!zero) path << (joined ? " L" : " M") << x << ',' << y;
      joined = !zero;
      o << "<circle cx=\"" << x << "\" cy=\"" << y << "\" r=\"3\" fill=\"" << colour << "\"/>\n";
    }
    if (path.tellp() > 0)
      o << "<path d=\"" << path.str().substr(1) << "\" fill=\"none\" stroke=\"" << colour
        << "\" stroke-width=\"1.5\"/>\n";
    o << "<text x=\"" << kWidth - kRight + 10 << "\" y=\"" << kTop + 15 + 18 * k << "\" fill=\""
      << colour << "\">" << xml_text(s.label) << "</text>\n";
  }
}

void write_panel(std::ostream& o, const Chart& chart) {
  std::vector<double> xs, ys;
  for (const Series& s : chart.series) {
    xs.insert(xs.end(), s.x.begin(), s.x.end());
    ys.insert(ys.end(), s.y.begin(), s.y.end());
  }
  if (!chart.x_categories.empty())
    xs = {0.0, double(chart.x_categories.size() - 1)};  // failed ones too
  const Axis ax = fit_axis(xs, chart.log_x, Zero::unless_crowded);
  const Axis ay = fit_axis(ys, chart.log_y, Zero::always);
  Frame f;
  if (has_zero_on_log_y(chart)) f.band = kZeroBand;
  o << "<text x=\"" << kLeft + f.w / 2 << "\" y=\"22\" font-size=\"14\" text-anchor=\"middle\">"
    << xml_text(chart.title) << "</text>\n";
  if (!chart.note.empty())
    o << "<text x=\"" << kLeft << "\" y=\"" << kTop - 6 << "\" font-size=\"10\">"
      << xml_text(chart.note) << "</text>\n";
  o << "<rect x=\"" << kLeft << "\" y=\"" << kTop << "\" width=\"" << f.w << "\" height=\""
    << f.axis_h() << "\" fill=\"none\" stroke=\"black\"/>\n";
  write_x_ticks(o, chart, ax, f);
  write_y_ticks(o, ay, f);
  o << "<text x=\"" << kLeft + f.w / 2 << "\" y=\"" << kHeight - 15 << "\" text-anchor=\"middle\">"
    << xml_text(chart.x_label) << "</text>\n";
  // Between the tick labels and the ticks (at x = 18 it ran through the labels).
  o << "<text transform=\"translate(" << kLeft - 16 << ',' << kTop + f.axis_h() / 2
    << ") rotate(-90)\" text-anchor=\"middle\">" << xml_text(chart.y_label) << "</text>\n";
  write_series(o, chart, ax, ay, f);
}

}  // namespace

std::string render_svg(const std::vector<Chart>& panels) {
  std::ostringstream o;
  o << "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"" << kWidth << "\" height=\""
    << kHeight * double(panels.size()) << "\" font-family=\"sans-serif\" font-size=\"12\">\n"
    << "<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n";
  for (std::size_t k = 0; k < panels.size(); ++k) {
    o << "<g transform=\"translate(0," << kHeight * double(k) << ")\">\n";
    write_panel(o, panels[k]);
    o << "</g>\n";
  }
  o << "</svg>\n";
  return o.str();
}

std::string render_svg(const Chart& chart) {
  return render_svg(std::vector<Chart>{chart});
}

}  // namespace beampack::tools
