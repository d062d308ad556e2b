// beampack-bench: Google Benchmark's main, with the host's SIMD in every report's context. The
// tracer's packet rate depends on the rays per packet Embree traverses natively (16 with
// AVX-512, 8 with AVX2: BENCHMARKS.md), so a figure is read with that width beside it.
#include <benchmark/benchmark.h>

#include <string>

#include "engine/embree_scene.h"

namespace {

std::string embree_native_packet() {
  const int rays = beampack::embree_native_packet_width();
  return rays > 0 ? std::to_string(rays) + " rays" : "unknown (rtcNewDevice failed)";
}

std::string host_simd() {
  __builtin_cpu_init();
  if (__builtin_cpu_supports("avx512f")) return "AVX-512";
  if (__builtin_cpu_supports("avx2")) return "AVX2";
  if (__builtin_cpu_supports("sse4.2")) return "SSE4.2";
  return "below SSE4.2";
}

}  // namespace

int main(int argc, char** argv) {
  benchmark::Initialize(&argc, argv);
  if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
  benchmark::AddCustomContext("host_simd", host_simd());
  benchmark::AddCustomContext("embree_native_packet", embree_native_packet());
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
