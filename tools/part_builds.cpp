#include "tools/part_builds.h"

#include <cstdio>

#include "engine/build_info.h"
#include "geometry/error.h"

namespace beampack::tools {

namespace {

bool same_build(const PartBuild& a, const PartBuild& b) {
  return a.revision != kUnknownRevision && a.revision == b.revision &&
         a.build_type == b.build_type && a.compiler == b.compiler && a.flags == b.flags;
}

// "RelWithDebInfo, gcc 12.2.0, flags "-O2 -g -DNDEBUG""
std::string built_as(const PartBuild& b) {
  return b.build_type + ", " + b.compiler + ", flags \"" + b.flags + "\"";
}

}  // namespace

PartBuild this_build() {
  const BuildInfo b = build_info();
  return {b.revision, b.build_type, b.compiler, b.flags};
}

void write_part_builds(StateWriter& w, const std::vector<PartBuild>& parts) {
  w.value<std::uint64_t>(parts.size());
  for (const PartBuild& p : parts) {
    w.text(p.revision);
    w.text(p.build_type);
    w.text(p.compiler);
    w.text(p.flags);
  }
}

std::vector<PartBuild> read_part_builds(StateReader& r, const std::string& path) {
  const auto count = r.value<std::uint64_t>();
  if (count == 0 || count > 1'000'000)
    throw InputError(path + ": damaged checkpoint: " + std::to_string(count) +
                     " builds of the run's parts, expected 1 to 1000000");
  std::vector<PartBuild> parts;
  for (std::uint64_t k = 0; k < count; ++k) {
    PartBuild p;
    p.revision = r.text();
    if (!is_revision_text(p.revision))
      throw InputError(path + ": damaged checkpoint: the revision of part " + std::to_string(k) +
                       " is not 1 to " + std::to_string(kMaxRevisionLength) +
                       " printable characters without spaces");
    p.build_type = r.text();  // any text: the checksum finds damage
    p.compiler = r.text();
    p.flags = r.text();
    parts.push_back(std::move(p));
  }
  return parts;
}

void warn_of_another_build(const PartBuild& last) {
  const PartBuild ours = this_build();
  if (same_build(last, ours)) return;
  const char* consequence =
      "the run goes on, but its numbers may differ from those of one build running it whole";
  if (last.revision == kUnknownRevision || ours.revision == kUnknownRevision)
    std::fprintf(stderr,
                 "beampack: warning: --resume: the revision of %s is unknown, so the checkpoint "
                 "may come from another build: %s\n",
                 last.revision == ours.revision      ? "both builds"
                 : last.revision == kUnknownRevision ? "the build that wrote the checkpoint"
                                                     : "this build",
                 consequence);
  else if (last.revision != ours.revision)
    std::fprintf(stderr,
                 "beampack: warning: --resume: the checkpoint was written by beampack %s and "
                 "this is beampack %s: %s\n",
                 last.revision.c_str(), ours.revision.c_str(), consequence);
  else
    std::fprintf(stderr,
                 "beampack: warning: --resume: the checkpoint was written by beampack %s built "
                 "as %s, and this one is built as %s: %s\n",
                 last.revision.c_str(), built_as(last).c_str(), built_as(ours).c_str(),
                 consequence);
}

nlohmann::json part_build_json(const PartBuild& part) {
  return {{"revision", part.revision},
          {"build_type", part.build_type},
          {"compiler", part.compiler},
          {"flags", part.flags}};
}

nlohmann::json part_builds_json(const std::vector<PartBuild>& parts) {
  nlohmann::json j = nlohmann::json::array();
  for (const PartBuild& p : parts) j.push_back(part_build_json(p));
  return j;
}

}  // namespace beampack::tools
