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
};

std::string render_svg(const Chart& chart);

}  // namespace beampack::tools
