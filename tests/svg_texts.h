#pragma once
// What a chart's SVG says: the text of its <text> elements.
#include <regex>
#include <string>
#include <vector>

namespace beampack::testing {

// The text of every <text> element whose attributes contain `attribute`, in order: `y="380"`
// picks the (first panel's) x axis tick labels, `x="8"` the y axis's.
inline std::vector<std::string> svg_texts(const std::string& svg,
                                          const std::string& attribute = "") {
  std::vector<std::string> out;
  const std::regex text("<text[^>]*" + attribute + "[^>]*>([^<]*)</text>");
  for (auto it = std::sregex_iterator(svg.begin(), svg.end(), text); it != std::sregex_iterator();
       ++it)
    out.push_back((*it)[1]);
  return out;
}

}  // namespace beampack::testing
