#pragma once
// Minimal SVG line charts for sweep.svg and convergence.svg: no plotting dependency.
#include <string>
#include <vector>

namespace beampack::tools {

struct Series {
  std::string label;
  std::vector<double> x, y;  // drawn in the given order; y = 0 on a log y axis: the 0 band
};

struct Chart {
  std::string title, x_label, y_label;
  bool log_x = false, log_y = false;
  std::vector<Series> series;
  // Names for x = 0, 1, 2, ... (a sweep of a text key): the x axis shows them instead of numbers.
  std::vector<std::string> x_categories = {};
  std::string note = {};  // a line under the title: what the chart leaves out
  // A linear x axis starts at 0 only where the values still fill half of it (1000..1002 would
  // sit in its last 0.2%); a linear y axis starts at 0 whenever its values are >= 0 (a fraction's
  // size is the point).
};

std::string render_svg(const Chart& chart);
// Panels stacked top to bottom in one chart, each with its own axes.
std::string render_svg(const std::vector<Chart>& panels);

// Text as XML 1.0 character data: & < > escaped, and what XML 1.0 forbids (control characters
// other than tab and line breaks, bytes that are not UTF-8) written as the text \xNN.
std::string xml_text(const std::string& text);

}  // namespace beampack::tools
