#include "tools/svg_plot.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <sstream>

namespace beampack::tools {
namespace {

constexpr double kWidth = 640, kHeight = 420, kLeft = 80, kRight = 160, kTop = 40, kBottom = 60;
const char* kColours[] = {"#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b"};

struct Axis {
  double lo = 0, hi = 1;
  bool log = false;
  double map(double v) const {
    const double a = log ? std::log10(v) : v;
    return (a - lo) / (hi - lo);
  }
};

Axis fit_axis(const std::vector<double>& values, bool log) {
  double lo = std::numeric_limits<double>::infinity(), hi = -lo;
  for (double v : values) {
    if (!std::isfinite(v) || (log && v <= 0)) continue;
    const double a = log ? std::log10(v) : v;
    lo = std::min(lo, a);
    hi = std::max(hi, a);
  }
  if (!std::isfinite(lo)) lo = 0, hi = 1;
  if (log) lo = std::floor(lo), hi = std::ceil(hi);
  if (hi - lo < 1e-12) {  // one value: a span around it, not [v, v + 1]
    const double half = log || lo == 0 ? 1.0 : 0.5 * std::abs(lo);
    lo -= log ? 0.0 : half, hi += half;
  }
  if (!log) {
    const double pad = 0.05 * (hi - lo);
    lo = std::min(lo, 0.0) == 0.0 && lo >= 0 ? 0.0 : lo - pad;
    hi += pad;
  }
  return {lo, hi, log};
}

std::string tick_label(double a, bool log) {
  char buf[32];
  if (log) std::snprintf(buf, sizeof buf, "1e%d", int(std::lround(a)));
  else std::snprintf(buf, sizeof buf, "%.3g", std::abs(a) < 1e-12 ? 0.0 : a);
  return buf;
}

// Tick positions (in axis units: log10 on a log axis) at whole decades, or at a 1-2-5 step,
// about five to a side; each label appears once.
std::vector<double> ticks(const Axis& a) {
  const double span = a.hi - a.lo;
  double step =
      a.log ? std::max(1.0, std::ceil(span / 6)) : std::pow(10.0, std::floor(std::log10(span / 5)));
  if (!a.log) {
    for (double m : {2.0, 5.0, 10.0})
      if (span / step > 7) step = std::pow(10.0, std::floor(std::log10(span / 5))) * m;
  }
  std::vector<double> t;
  const double first = std::ceil(a.lo / step - 1e-9) * step;
  for (int k = 0; k < 20; ++k) {  // by index: a step below the values' last digit cannot stall
    const double v = first + k * step;
    if (v > a.hi + 1e-9 * span) break;
    if (t.empty() || v > t.back()) t.push_back(v);
  }
  return t;
}

// Text as XML character data: a swept file name `a&b.xyz` or `c<d.xyz` made the chart malformed.
std::string xml_text(const std::string& text) {
  std::string out;
  for (const char c : text) {
    switch (c) {
      case '&':
        out += "&amp;";
        break;
      case '<':
        out += "&lt;";
        break;
      case '>':
        out += "&gt;";
        break;
      default:
        out += c;
    }
  }
  return out;
}

}  // namespace

std::string render_svg(const Chart& chart) {
  std::vector<double> xs, ys;
  for (const Series& s : chart.series) {
    xs.insert(xs.end(), s.x.begin(), s.x.end());
    ys.insert(ys.end(), s.y.begin(), s.y.end());
  }
  if (!chart.x_categories.empty())
    xs = {0.0, double(chart.x_categories.size() - 1)};  // failed ones too
  const Axis ax = fit_axis(xs, chart.log_x), ay = fit_axis(ys, chart.log_y);
  const double w = kWidth - kLeft - kRight, h = kHeight - kTop - kBottom;
  auto px = [&](double x) { return kLeft + w * ax.map(x); };
  auto py = [&](double y) { return kTop + h * (1 - ay.map(y)); };
  std::ostringstream o;
  o << "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"" << kWidth << "\" height=\"" << kHeight
    << "\" font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"100%\" height=\"100%\" "
       "fill=\"white\"/>\n";
  o << "<text x=\"" << kWidth / 2 - 60 << "\" y=\"22\" font-size=\"14\">" << xml_text(chart.title)
    << "</text>\n";
  o << "<rect x=\"" << kLeft << "\" y=\"" << kTop << "\" width=\"" << w << "\" height=\"" << h
    << "\" fill=\"none\" stroke=\"black\"/>\n";
  const bool categories = !chart.x_categories.empty();
  std::vector<double> x_ticks = ticks(ax);
  if (categories) {
    x_ticks.clear();
    for (std::size_t k = 0; k < chart.x_categories.size(); ++k) x_ticks.push_back(double(k));
  }
  for (double fx : x_ticks) {
    const double x = kLeft + w * (fx - ax.lo) / (ax.hi - ax.lo);
    const std::string label =
        categories ? chart.x_categories[std::size_t(std::lround(fx))] : tick_label(fx, ax.log);
    o << "<line x1=\"" << x << "\" y1=\"" << kTop + h << "\" x2=\"" << x << "\" y2=\""
      << kTop + h + 5 << "\" stroke=\"black\"/>"
      << "<text x=\"" << x - 15 << "\" y=\"" << kTop + h + 20 << "\">" << xml_text(label)
      << "</text>\n";
  }
  for (double fy : ticks(ay)) {
    const double y = kTop + h * (1 - (fy - ay.lo) / (ay.hi - ay.lo));
    o << "<line x1=\"" << kLeft - 5 << "\" y1=\"" << y << "\" x2=\"" << kLeft << "\" y2=\"" << y
      << "\" stroke=\"black\"/>"
      << "<text x=\"" << 8 << "\" y=\"" << y + 4 << "\">" << tick_label(fy, ay.log) << "</text>\n";
  }
  o << "<text x=\"" << kLeft + w / 2 - 40 << "\" y=\"" << kHeight - 15 << "\">"
    << xml_text(chart.x_label) << "</text>\n";
  o << "<text transform=\"translate(18," << kTop + h / 2 + 40 << ") rotate(-90)\">"
    << xml_text(chart.y_label) << "</text>\n";
  bool zeros = false;  // on a log y axis a 0 sits on the lower edge as a hollow circle
  for (std::size_t k = 0; k < chart.series.size(); ++k) {
    const Series& s = chart.series[k];
    const char* colour = kColours[k % 6];
    std::ostringstream path;
    for (std::size_t i = 0; i < s.x.size(); ++i) {
      if (!std::isfinite(s.y[i]) || (chart.log_y && s.y[i] < 0) || (chart.log_x && s.x[i] <= 0))
        continue;
      const bool zero = chart.log_y && s.y[i] == 0;
      zeros = zeros || zero;
      const double y = zero ? kTop + h : py(s.y[i]);
      path << (path.tellp() == 0 ? "M" : " L") << px(s.x[i]) << ',' << y;
      o << "<circle cx=\"" << px(s.x[i]) << "\" cy=\"" << y << "\" r=\"3\" fill=\""
        << (zero ? "white" : colour) << "\" stroke=\"" << colour << "\"/>\n";
    }
    o << "<path d=\"" << path.str() << "\" fill=\"none\" stroke=\"" << colour
      << "\" stroke-width=\"1.5\"/>\n";
    o << "<text x=\"" << kWidth - kRight + 10 << "\" y=\"" << kTop + 15 + 18 * k << "\" fill=\""
      << colour << "\">" << xml_text(s.label) << "</text>\n";
  }
  if (zeros)
    o << "<text x=\"" << kWidth - kRight + 10 << "\" y=\"" << kTop + h
      << "\" font-size=\"10\">hollow: 0</text>\n";
  o << "</svg>\n";
  return o.str();
}

}  // namespace beampack::tools
