// contact/: the contact graph of the paper's random-overlap packing (L = 0.325), N = 1e4 .. 1e6.
#include <benchmark/benchmark.h>

#include "geometry/contact.h"
#include "geometry/packing.h"

namespace {

void contact_search(benchmark::State& state) {
  const auto n = static_cast<std::size_t>(state.range(0));
  const beampack::Particles p = beampack::random_overlap_packing(n, 1e-3, 0.325, 1);
  std::size_t pairs = 0;
  for (auto _ : state) {
    auto contacts = beampack::find_contacts(p);
    pairs = contacts.size();
    benchmark::DoNotOptimize(contacts.data());
  }
  state.counters["pairs"] = double(pairs);
  state.counters["particles/s"] =
      benchmark::Counter(double(n), benchmark::Counter::kIsIterationInvariantRate);
}

}  // namespace

BENCHMARK(contact_search)
    ->Name("contact/search")
    ->RangeMultiplier(10)
    ->Range(10'000, 1'000'000)
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();
