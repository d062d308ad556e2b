#pragma once
// Sums that keep the low-order bits each addition rounds away: a running total held as
// value + low (a double-double), value always the total rounded to a double. A million equal ray
// energies add up to their total within an ulp, where a plain sum drifts by ~1e-11 of it (and the
// ledger of twenty pulses by ~1e-10). Deterministic: the same terms in the same order give the
// same bits. Needs IEEE arithmetic (no -ffast-math, which would reassociate the correction away).

namespace beampack {

// value + low += x. value stays the rounded total, so readers of value alone see the best double.
inline void add_compensated(double& value, double& low, double x) {
  const double s = value + x;
  const double b = s - value;
  low += (value - (s - b)) + (x - b);  // what s rounded away: s + that = value + x exactly
  const double total = s + low;
  low -= total - s;
  value = total;
}

class CompensatedSum {
 public:
  void add(double x) { add_compensated(value_, low_, x); }
  double value() const { return value_; }

 private:
  double value_ = 0.0;
  double low_ = 0.0;
};

}  // namespace beampack
