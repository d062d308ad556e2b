#pragma once
// Sums that keep the low-order bits each addition rounds away: a running total held as
// value + low (a double-double), value always the total rounded to a double. A million equal ray
// energies add up to their total within an ulp, where a plain sum drifts by ~1e-11 of it (and the
// ledger of twenty pulses by ~1e-10). Deterministic: the same terms in the same order give the
// same bits. Needs IEEE arithmetic (no -ffast-math, which would reassociate the correction away).

#include <cmath>

namespace beampack {

// a + b rounded, and the exact error of that rounding: sum + error = a + b (Knuth's TwoSum).
inline double two_sum(double a, double b, double& error) {
  const double sum = a + b, b_part = sum - a;
  error = (a - (sum - b_part)) + (b - b_part);
  return sum;
}

// value + low += x. value stays the rounded total, so readers of value alone see the best double.
inline void add_compensated(double& value, double& low, double x) {
  double rounded_away;
  const double s = two_sum(value, x, rounded_away);
  low += rounded_away;
  const double total = s + low;
  low -= total - s;
  value = total;
}

class CompensatedSum {
 public:
  void add(double x) { add_compensated(value_, low_, x); }
  double value() const { return value_; }
  double low() const { return low_; }  // what value rounded away from the total

 private:
  double value_ = 0.0;
  double low_ = 0.0;
};

// a / b of two compensated sums, rounded once from nearly the exact quotient of their totals:
// k of N equal volumes give k / N as a double, where the two rounded values' quotient could be an
// ulp off it (60 of 1000 printed 0.060000000000000005). The remainder a - q b is exact by fma.
inline double compensated_ratio(const CompensatedSum& a, const CompensatedSum& b) {
  const double q = a.value() / b.value();
  if (!std::isfinite(q) || !std::isfinite(b.value())) return q;  // fma(-q, inf, a) is NaN
  const double remainder = std::fma(-q, b.value(), a.value()) + (a.low() - q * b.low());
  return q + remainder / b.value();
}

}  // namespace beampack
