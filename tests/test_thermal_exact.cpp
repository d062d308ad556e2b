// Closed-form and exact-discrete solutions of the conduction step (3.10): the lumped model (1.2),
// its convergence order, two-particle exchange and a chain against the matrix exponential.
#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>
#include <algorithm>
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

// Two walls at different temperatures, conductance g each, hold a sphere at their mean plus its
// power over 2 g; one implicit step is theta1 = (c theta0 + dt (g 300 + g 400 + P)) / (c + 2 dt g),
// in either order of the walls (the first one's temperature is the solve's reference). Every
// other test's walls share a temperature, which a source built from the first wall's alone passed.
TEST(ThermalExact, ASphereBetweenWallsAtTwoTemperaturesTakesTheirMean) {
  const Lumped l;
  const double g = l.k * l.area / l.length, c = l.capacity(), power = 20.0 * g;
  const double dt = 0.1 * c / g;
  for (const bool hot_first : {false, true}) {
    Particles p;
    p.add(Vec3(l.radius, 0, 0), l.radius, 0, 300.0);
    ThermalSpec spec;
    spec.time_scaling = l.scaling;
    spec.walls = {{0, 0.0, 0.0, hot_first ? 400.0 : 300.0, g},
                  {0, 2.0 * l.radius, 0.0, hot_first ? 300.0 : 400.0, g}};
    ThermalModel model(p, {l.material}, spec);
    model.step(dt, {power * dt});
    EXPECT_NEAR(p.temperature[0], (c * 300.0 + dt * (700.0 * g + power)) / (c + 2.0 * dt * g), 1e-9)
        << "hot wall first: " << hot_first;
    for (int step = 0; step < 2000; ++step) model.step(dt, {power * dt});
    EXPECT_NEAR(p.temperature[0], 350.0 + power / (2.0 * g), 1e-6) << hot_first;
    // The heat from the hot wall and the beam's left through the cold one, less what it kept.
    const ThermalLedger& e = model.ledger();
    EXPECT_NEAR(e.imbalance(), 0.0, 1e-12 * e.absorbed) << hot_first;
  }
}

double measured_order(double phi) {
  const Lumped lumped;
  const double t_end = 2.0 * lumped.tau();
  const double e1 = std::abs(lumped.simulate(phi, 40, t_end) - lumped.exact(t_end));
  const double e2 = std::abs(lumped.simulate(phi, 80, t_end) - lumped.exact(t_end));
  return std::log2(e1 / e2);
}

// Two overlapping spheres of different size and material, at 500 and 300 K, with their contact's
// conductance G, their thermal masses m C / M by hand (section 1, 4.1; M = 1e6 by default: rho
// 4/3 pi r^3 C_S / M) and the rate G (1/c1 + 1/c2) at which their difference decays.
struct TwoSpheres {
  Particles p;
  Material a, b;
  std::vector<Contact> contacts;
  double g = 0, rate = 0;
  const double c1 = 1000.0 * 4.0 / 3.0 * std::numbers::pi * std::pow(1e-4, 3) * 1000.0 / 1e6;
  const double c2 = 3000.0 * 4.0 / 3.0 * std::numbers::pi * std::pow(0.8e-4, 3) * 700.0 / 1e6;
  TwoSpheres() {
    p.add(Vec3(0, 0, 0), 1e-4, 0, 500.0);
    p.add(Vec3(1.6e-4, 0, 0), 0.8e-4, 1, 300.0);
    a.conductivity = 50;
    b.conductivity = 150;
    b.density = 3000;
    b.c_solid = 700;
    contacts = find_contacts(p);
    const ContactGeometry geo = contact_geometry(1.6e-4, 1e-4, 0.8e-4);
    g = 0.5 * (50 + 150) * geo.area / geo.distance;
    rate = g * (1.0 / c1 + 1.0 / c2);
  }
};

// theta_1 - theta_2 decays as exp(-G (1/c1 + 1/c2) t) and c1 theta_1 + c2 theta_2 is constant.
class TwoParticles : public ::testing::TestWithParam<const char*> {};

TEST_P(TwoParticles, DifferenceDecaysExponentiallyEnergyConstant) {
  TwoSpheres two;
  auto& [p, a, b, contacts, g, rate, c1, c2] = two;
  ASSERT_EQ(contacts.size(), 1u);
  EXPECT_DOUBLE_EQ(contact_conductances(p, {a, b}, contacts)[0], g);

  ThermalSpec spec;
  spec.phi = 0.5;
  spec.solver = GetParam();
  ThermalModel model(p, {a, b}, spec);
  model.set_contacts(contacts);
  EXPECT_NEAR(model.thermal_mass(0) / c1, 1.0, 1e-14);
  EXPECT_NEAR(model.thermal_mass(1) / c2, 1.0, 1e-14);
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

// The explicit step (phi = 0) on the same two spheres, against its own algebra rather than the
// exponential: theta^{n+1} = theta^n + dt Q(theta^n) / c gives each sphere -dt G d^n / c_i, so the
// difference d = theta_1 - theta_2 shrinks by exactly (1 - rate dt) a step, rate = G (1/c1 +
// 1/c2), while c1 theta_1 + c2 theta_2 stays fixed. After 100 steps of rate dt = 0.01 this is
// 200 x 0.99^100 = 73.2 K, which differs from the exponential's 200 e^{-1} by 0.5% and from
// backward Euler's 200 / 1.01^100 by 1%: 1e-12 tells them apart, and any slip in the explicit
// update's conductance, capacity or dt (only round-off, ~1e-14 here, is allowed).
TEST(ThermalExact, ExplicitStepShrinksTheDifferenceByOneMinusRateDtEachStep) {
  TwoSpheres two;
  auto& [p, a, b, contacts, g, rate, c1, c2] = two;
  ASSERT_EQ(contacts.size(), 1u);
  ThermalSpec spec;
  spec.phi = 0;
  ThermalModel model(p, {a, b}, spec);
  model.set_contacts(contacts);
  const double dt = 0.01 / rate;
  // The step is within the explicit limit min_i c_i / G (C_S < C_L for both): one step, no split.
  EXPECT_NEAR(model.monotone_step_limit(), std::min(c1, c2) / g, 1e-12 * std::min(c1, c2) / g);
  const double energy0 = c1 * p.temperature[0] + c2 * p.temperature[1];
  const int steps = 100;
  for (int s = 0; s < steps; ++s) {
    const StepReport r = model.step(dt, {});
    ASSERT_EQ(r.solver, "explicit");
    ASSERT_EQ(r.substeps, 1);
  }
  const double shrink = std::pow(1.0 - rate * dt, steps);
  const double difference = 200.0 * shrink;
  EXPECT_NEAR((p.temperature[0] - p.temperature[1]) / difference, 1.0, 1e-12);
  // Each sphere: the mean c-weighted temperature plus its share of the difference.
  const double mean = energy0 / (c1 + c2);
  EXPECT_NEAR(p.temperature[0], mean + c2 / (c1 + c2) * difference, 1e-12 * mean);
  EXPECT_NEAR(p.temperature[1], mean - c1 / (c1 + c2) * difference, 1e-12 * mean);
  const double energy = c1 * p.temperature[0] + c2 * p.temperature[1];
  EXPECT_NEAR(energy / energy0, 1.0, 1e-13);
  EXPECT_NEAR(model.ledger().stored, 0.0, 1e-12 * energy0);
  // The answer is not the continuous one: the assertion above could tell an implicit step apart.
  EXPECT_GT(std::abs(shrink / std::exp(-rate * dt * steps) - 1.0), 1e-3);
}

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

// Eight spheres in a row, alternating a light (K = 20) and a heavy (K = 80, rho = 4000) material,
// at 300 .. 475 K, the first touching a wall at 250 K: contacts, a wall and two materials. The
// exact system (3.2) and the wall rule are assembled by hand, independently of the model.
struct Chain {
  static constexpr int n = 8;
  static constexpr double a = 1e-4;
  Material light, heavy;
  Eigen::MatrixXd lw;
  Eigen::VectorXd c, b, theta0;

  Chain() {
    light.conductivity = 20;
    heavy.conductivity = 80;
    heavy.density = 4000;
    const Particles p = particles();
    // Neighbours a apart, radii 0.6 a: lens radius^2 = (0.6 a)^2 - (a / 2)^2 = 0.11 a^2 (3.9),
    // G = (K_k + K_k+1) / 2 x pi 0.11 a^2 / a (3.2), written here, not taken from the code.
    std::vector<Contact> hand;
    for (std::uint32_t k = 0; k + 1 < n; ++k)
      hand.push_back({k, k + 1, std::numbers::pi * 0.11 * a * a, a});
    const auto contacts = find_contacts(p);  // what the model will use: the same graph
    EXPECT_EQ(contacts.size(), hand.size());
    for (std::size_t k = 0; k < std::min(contacts.size(), hand.size()); ++k) {
      EXPECT_EQ(contacts[k].j, hand[k].j);
      EXPECT_NEAR(contacts[k].area / hand[k].area, 1.0, 1e-14) << k;
      EXPECT_NEAR(contacts[k].distance / hand[k].distance, 1.0, 1e-14) << k;
    }
    lw = test::dense_conduction(n, hand, [](const Contact& ct) {
      return 0.5 * ((ct.i % 2 ? 80 : 20) + (ct.j % 2 ? 80 : 20)) * ct.area / ct.distance;
    });
    const double g_wall = std::numbers::pi * 20 * 0.6 * a;
    lw(0, 0) += g_wall;
    b = Eigen::VectorXd::Zero(n);
    b[0] = g_wall * 250.0;
    // m C / M by hand: rho 4/3 pi (0.6 a)^3 C_S / M with rho = 1000 (even k) or 4000 (odd k),
    // C_S = 1000 and M = 1e6 (the defaults).
    c.resize(n), theta0.resize(n);
    for (int k = 0; k < n; ++k) {
      const double rho = k % 2 ? 4000.0 : 1000.0;
      c[k] = rho * 4.0 / 3.0 * std::numbers::pi * std::pow(0.6 * a, 3) * 1000.0 / 1e6;
      theta0[k] = p.temperature[k];
    }
  }
  Particles particles() const {
    Particles p = test::chain(n, a);
    for (int k = 0; k < n; ++k) {
      p.material[k] = k % 2;
      p.temperature[k] = 300.0 + 25.0 * k;  // 300 .. 475 K
    }
    return p;
  }
  ThermalSpec spec(double phi) const {
    ThermalSpec s;
    s.phi = phi;
    s.solver = "direct";
    s.tolerance = 1e-12;
    s.walls.push_back({0, 0.0, 0.0, 250.0, -1.0});  // the first sphere touches x = 0
    return s;
  }
  Eigen::VectorXd exact(double t) const { return chain_exact(lw, c, b, theta0, t); }
  Eigen::VectorXd eigenvalues() const {
    return Eigen::GeneralizedSelfAdjointEigenSolver<Eigen::MatrixXd>(
               lw, Eigen::MatrixXd(c.asDiagonal()))
        .eigenvalues();
  }
  // The largest error over the chain after `steps` equal steps to t_end; each must be one step
  // (no sub-steps, which would change the step length the order is measured in).
  double error(double phi, int steps, double t_end) const {
    Particles p = particles();
    ThermalModel model(p, {light, heavy}, spec(phi));
    model.set_contacts(find_contacts(p));
    for (int s = 0; s < steps; ++s) EXPECT_EQ(model.step(t_end / steps, {}).substeps, 1);
    const Eigen::VectorXd theta = Eigen::Map<const Eigen::VectorXd>(p.temperature.data(), n);
    return (theta - exact(t_end)).cwiseAbs().maxCoeff();
  }
};

TEST(ThermalExact, ChainMatchesMatrixExponential) {
  const Chain chain;
  const int n = Chain::n;
  Particles p = chain.particles();
  ThermalModel model(p, {chain.light, chain.heavy}, chain.spec(0.5));
  model.set_contacts(find_contacts(p));
  // The model's own masses must agree with those by hand.
  for (int k = 0; k < n; ++k)
    EXPECT_NEAR(model.thermal_mass(static_cast<std::size_t>(k)) / chain.c[k], 1.0, 1e-14) << k;

  const Eigen::VectorXd lambda = chain.eigenvalues();
  const double slowest = lambda.minCoeff(), fastest = lambda.maxCoeff();
  const double t_end = 1.0 / slowest;
  const int steps = 4000;
  for (int s = 0; s < steps; ++s) model.step(t_end / steps, {});
  const Eigen::VectorXd exact = chain.exact(t_end);
  // CN error ~ (lambda dt)^2 / 12 per unit time for the fastest mode that is still alive:
  // 4.1e-7 K measured; backward Euler's first-order error would be ~1e-2 K.
  const double dt_lambda = fastest * t_end / steps;
  ASSERT_LT(dt_lambda, 1.0);
  for (int k = 0; k < n; ++k) EXPECT_NEAR(p.temperature[k], exact[k], 1e-5) << "particle " << k;
  EXPECT_GT((exact - chain.theta0).cwiseAbs().maxCoeff(), 10.0);  // the solution did move
}

// The order of the step on a scene with contacts (the lumped sphere above has none): from 400 to
// 800 steps over t_end = 1 / lambda_min, the error of the explicit and backward-Euler steps
// halves (9.8e-2 -> 4.9e-2 K measured) and that of Crank-Nicolson quarters (4.1e-5 -> 1.0e-5 K).
// 400 steps is 0.55 times the explicit limit (fewer would be split into sub-steps, which
// Chain::error refuses: at 200 steps the explicit error equalled 400 steps' to the digit).
double chain_order(double phi) {
  const Chain chain;
  const double t_end = 1.0 / chain.eigenvalues().minCoeff();
  return std::log2(chain.error(phi, 400, t_end) / chain.error(phi, 800, t_end));
}

// The theta method's order: 1 for explicit (phi = 0) and backward Euler (1), 2 for
// Crank-Nicolson (1/2), on the lumped sphere (walls only: the explicit step's "diagonal" path;
// dt = tau / 20 and tau / 40, within its limit tau) and on the conducting chain.
TEST(ThermalExact, ConvergenceOrderIsOneForEulerAndTwoForCrankNicolson) {
  for (const auto& [phi, order] : {std::pair{0.0, 1.0}, {1.0, 1.0}, {0.5, 2.0}}) {
    EXPECT_NEAR(measured_order(phi), order, 0.05) << "lumped sphere, phi = " << phi;
    EXPECT_NEAR(chain_order(phi), order, 0.05) << "chain, phi = " << phi;
  }
}

}  // namespace
}  // namespace beampack
