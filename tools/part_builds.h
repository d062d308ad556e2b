#pragma once
// The builds that ran a run's parts: a checkpoint lists them, a resume compares the last with
// itself, and summary.json keeps the earlier ones. Bit-identical results are promised for one
// build only: one revision, build type, compiler and set of flags.
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "engine/state_io.h"

namespace beampack::tools {

struct PartBuild {
  std::string revision;                     // BuildInfo's; kUnknownRevision where no record says
  std::string build_type, compiler, flags;  // kUnknownRevision in a format-5 or -4 record
};

// This build, as its checkpoints record it.
PartBuild this_build();
// Checkpoint format 6: the count, then each part's revision, build type, compiler and flags.
void write_part_builds(StateWriter& w, const std::vector<PartBuild>& parts);
// InputError naming `path` for a record no build writes.
std::vector<PartBuild> read_part_builds(StateReader& r, const std::string& path);

// A resume by a build other than the one that wrote the checkpoint says so, once, on stderr.
// An unknown revision equals none, not even another unknown one.
void warn_of_another_build(const PartBuild& last);

// A build as summary.json records it: {revision, build_type, compiler, flags}, for this run's
// (under `beampack`, with the version) and each earlier part's.
nlohmann::json part_build_json(const PartBuild& part);
// summary.json's beampack.earlier_parts: one object per part.
nlohmann::json part_builds_json(const std::vector<PartBuild>& parts);

}  // namespace beampack::tools
