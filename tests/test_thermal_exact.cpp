// Closed-form and exact-discrete solutions of the conduction step (3.10): the lumped model (1.2),
// its convergence order, two-particle exchange and a chain against the matrix exponential.
#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>
#include <cmath>
#include <numbers>

#include "geometry/contact.h"
#include "tests/thermal_test_util.h"
#include "thermal/thermal_model.h"

namespace beampack {
namespace {

// One sphere of radius R touching walls x = 0 and x = 2R, each of conductance K A^c / L, so the
// total is the 2 K A^c / L of (1.1); constant absorbed power P; theta(0) = theta_w.
struct Lumped {
  double radius = 1e-3, k = 1.0, area = 1e-6, length = 1e-3, theta_w = 300.0, scaling = 1e6;
  Material material;
  double g_total() const { return 2.0 * k * area / length; }
  double capacity() const { return test::solid_capacity(material, radius, scaling); }
  double power() const { return 100.0 * g_total(); }  // 100 K steady rise, below theta_m
  double tau() const { return capacity() / g_total(); }
  // (1.2) with m C replaced by m C / M (section 4.1).
  double exact(double t) const {
    return theta_w + power() * length / (2.0 * k * area) * (1.0 - std::exp(-t / tau()));
  }
  double simulate(double phi, int steps, double t_end) const {
    Particles p;
    p.add(Vec3(radius, 0, 0), radius, 0, theta_w);
    ThermalSpec spec;
    spec.phi = phi;
    spec.time_scaling = scaling;
    for (double x : {0.0, 2.0 * radius})
      spec.walls.push_back({0, x, 0.0, theta_w, k * area / length});
    ThermalModel model(p, {material}, spec);
    const double dt = t_end / steps;
    for (int s = 0; s < steps; ++s) model.step(dt, {power() * dt});
    return p.temperature[0];
  }
};

TEST(ThermalExact, LumpedModelMatchesClosedForm) {
  const Lumped lumped;
  const double t_end = 3.0 * lumped.tau();
  const double theta = lumped.simulate(0.5, 2000, t_end);
  // Crank-Nicolson error ~ (dt / tau)^2 / 12 of the 100 K rise: ~1e-5 K here, 2.8e-6 K measured.
  EXPECT_NEAR(theta, lumped.exact(t_end), 1e-5);
  EXPECT_GT(theta - lumped.theta_w, 90.0);  // the test is not trivially near theta_w
}

double measured_order(double phi) {
  const Lumped lumped;
  const double t_end = 2.0 * lumped.tau();
  const double e1 = std::abs(lumped.simulate(phi, 40, t_end) - lumped.exact(t_end));
  const double e2 = std::abs(lumped.simulate(phi, 80, t_end) - lumped.exact(t_end));
  return std::log2(e1 / e2);
}

TEST(ThermalExact, ConvergenceOrderOneForBackwardEuler) {
  EXPECT_NEAR(measured_order(1.0), 1.0, 0.05);
}

TEST(ThermalExact, ConvergenceOrderTwoForCrankNicolson) {
  EXPECT_NEAR(measured_order(0.5), 2.0, 0.05);
}

// Two overlapping spheres of different size and material: theta_1 - theta_2 decays as
// exp(-G (1/c1 + 1/c2) t) and c1 theta_1 + c2 theta_2 is constant.
class TwoParticles : public ::testing::TestWithParam<const char*> {};

TEST_P(TwoParticles, DifferenceDecaysExponentiallyEnergyConstant) {
  Particles p;
  p.add(Vec3(0, 0, 0), 1e-4, 0, 500.0);
  p.add(Vec3(1.6e-4, 0, 0), 0.8e-4, 1, 300.0);
  Material a, b;
  a.conductivity = 50;
  b.conductivity = 150;
  b.density = 3000;
  b.c_solid = 700;
  const auto contacts = find_contacts(p);
  ASSERT_EQ(contacts.size(), 1u);
  const ContactGeometry geo = contact_geometry(1.6e-4, 1e-4, 0.8e-4);
  const double g = 0.5 * (50 + 150) * geo.area / geo.distance;
  EXPECT_DOUBLE_EQ(contact_conductances(p, {a, b}, contacts)[0], g);

  ThermalSpec spec;
  spec.phi = 0.5;
  spec.solver = GetParam();
  ThermalModel model(p, {a, b}, spec);
  model.set_contacts(contacts);
  // m C / M by hand (section 1, 4.1; M = 1e6 by default), each sphere with its own material and
  // radius: rho 4/3 pi r^3 C_S / M.
  const double c1 = 1000.0 * 4.0 / 3.0 * std::numbers::pi * std::pow(1e-4, 3) * 1000.0 / 1e6;
  const double c2 = 3000.0 * 4.0 / 3.0 * std::numbers::pi * std::pow(0.8e-4, 3) * 700.0 / 1e6;
  EXPECT_NEAR(model.thermal_mass(0) / c1, 1.0, 1e-14);
  EXPECT_NEAR(model.thermal_mass(1) / c2, 1.0, 1e-14);
  const double rate = g * (1.0 / c1 + 1.0 / c2);
  const double energy0 = c1 * p.temperature[0] + c2 * p.temperature[1];
  const double dt = 0.002 / rate;  // the fixed-point contraction dt phi 2G/c_min is < 0.002
  const int steps = 1000;
  for (int s = 0; s < steps; ++s) {
    const StepReport r = model.step(dt, {});
    ASSERT_EQ(r.solver, GetParam());
  }
  const double expected = 200.0 * std::exp(-rate * dt * steps);
  EXPECT_NEAR((p.temperature[0] - p.temperature[1]) / expected, 1.0, 1e-6);
  const double energy = c1 * p.temperature[0] + c2 * p.temperature[1];
  EXPECT_NEAR(energy / energy0, 1.0, 1e-13);
  EXPECT_NEAR(model.ledger().stored, 0.0, 1e-12 * energy0);
}

INSTANTIATE_TEST_SUITE_P(Solvers, TwoParticles, ::testing::Values("fixed-point", "cg", "direct"),
                         [](const auto& info) {
  std::string s = info.param;
  return s == "fixed-point" ? std::string("fixed_point") : s;
});

// Exact solution of the discrete system c theta' = b - (L + W) theta by the generalised symmetric
// eigenproblem (L + W) v = lambda C v (V^T C V = I):
//   theta(t) = theta* + V exp(-Lambda t) V^T C (theta0 - theta*),  theta* = (L + W)^{-1} b.
Eigen::VectorXd chain_exact(const Eigen::MatrixXd& lw, const Eigen::VectorXd& c,
                            const Eigen::VectorXd& b, const Eigen::VectorXd& theta0, double t) {
  Eigen::GeneralizedSelfAdjointEigenSolver<Eigen::MatrixXd> eig(lw,
                                                                Eigen::MatrixXd(c.asDiagonal()));
  const Eigen::MatrixXd& v = eig.eigenvectors();
  const Eigen::VectorXd steady = lw.ldlt().solve(b);
  const Eigen::VectorXd decay = (-eig.eigenvalues().array() * t).exp().matrix();
  return steady + v * decay.asDiagonal() * v.transpose() * c.asDiagonal() * (theta0 - steady);
}

TEST(ThermalExact, ChainMatchesMatrixExponential) {
  const int n = 8;
  const double a = 1e-4;
  Particles p = test::chain(n, a);
  Material light, heavy;
  light.conductivity = 20;
  heavy.conductivity = 80;
  heavy.density = 4000;
  for (int k = 0; k < n; ++k) {
    p.material[k] = k % 2;
    p.temperature[k] = 300.0 + 25.0 * k;  // 300 .. 475 K
  }
  ThermalSpec spec;
  spec.phi = 0.5;
  spec.solver = "direct";
  spec.tolerance = 1e-12;
  spec.walls.push_back({0, 0.0, 0.0, 250.0, -1.0});  // the first sphere touches x = 0
  ThermalModel model(p, {light, heavy}, spec);
  model.set_contacts(find_contacts(p));

  // The exact system, assembled independently of the model from (3.2) and the wall rule.
  Eigen::MatrixXd lw = test::dense_conduction(n, find_contacts(p), [](const Contact& ct) {
    return conductance(ct.i % 2 ? 80 : 20, ct.j % 2 ? 80 : 20, ct.area, ct.distance);
  });
  Eigen::VectorXd c(n), b = Eigen::VectorXd::Zero(n), theta0(n);
  const double g_wall = std::numbers::pi * 20 * 0.6 * a;
  lw(0, 0) += g_wall;
  b[0] = g_wall * 250.0;
  // m C / M by hand: rho 4/3 pi (0.6 a)^3 C_S / M with rho = 1000 (even k) or 4000 (odd k),
  // C_S = 1000 and M = 1e6 (the defaults); the model's own masses must agree.
  for (int k = 0; k < n; ++k) {
    const double rho = k % 2 ? 4000.0 : 1000.0;
    c[k] = rho * 4.0 / 3.0 * std::numbers::pi * std::pow(0.6 * a, 3) * 1000.0 / 1e6;
    theta0[k] = p.temperature[k];
    EXPECT_NEAR(model.thermal_mass(static_cast<std::size_t>(k)) / c[k], 1.0, 1e-14) << k;
  }

  Eigen::GeneralizedSelfAdjointEigenSolver<Eigen::MatrixXd> eig(lw,
                                                                Eigen::MatrixXd(c.asDiagonal()));
  const double slowest = eig.eigenvalues().minCoeff(), fastest = eig.eigenvalues().maxCoeff();
  const double t_end = 1.0 / slowest;
  const int steps = 4000;
  for (int s = 0; s < steps; ++s) model.step(t_end / steps, {});
  const Eigen::VectorXd exact = chain_exact(lw, c, b, theta0, t_end);
  // CN error ~ (lambda dt)^2 / 12 per unit time for the fastest mode that is still alive:
  // 4.1e-7 K measured; backward Euler's first-order error would be ~1e-2 K.
  const double dt_lambda = fastest * t_end / steps;
  ASSERT_LT(dt_lambda, 1.0);
  for (int k = 0; k < n; ++k) EXPECT_NEAR(p.temperature[k], exact[k], 1e-5) << "particle " << k;
  EXPECT_GT((exact - theta0).cwiseAbs().maxCoeff(), 10.0);  // the solution did move
}

}  // namespace
}  // namespace beampack
