#pragma once
// Minimal SVG line charts for sweep.svg and convergence.svg: no plotting dependency.
#include <string>
#include <vector>

namespace beampack::tools {

struct Series {
  std::string label;
  std::vector<double> x, y;
};

struct Chart {
  std::string title, x_label, y_label;
  bool log_x = false, log_y = false;
  std::vector<Series> series;
  // Names for x = 0, 1, 2, ... (a sweep of a text key): the x axis shows them instead of numbers.
  std::vector<std::string> x_categories = {};
};

std::string render_svg(const Chart& chart);

}  // namespace beampack::tools
