// Garment law unit tests: *LAPLACE PRESSURE with REFERENCE=alpha, through the model and the analysis.
//  - Circle of radius R0 cut into equal chords, T3 or straight-sided T6 (as calfit's leg meshes): the reference
//    share's nodal pressures are T / R0, so REFERENCE=1 is the follower pressure T / R0 (*DLOAD on every face):
//    the same external force at any u, the same solution, and laplace_pressure = T / R0 at every skin node
//    (round-off). T6 quadratic arcs: the same to the discretisation (p0 = (1 - theta^2 / 12) T / R0, theta the
//    face's central angle), the difference falling as 1/n^2.
//  - The load is affine in alpha: R(alpha) = (1 - alpha) R(0) + alpha R(1) at the same u (ellipse with a
//    tension profile, T3 and T6); REFERENCE=0 is the deck without REFERENCE to the bit.
//  - Deck errors: REFERENCE outside [0, 1], not a number; the file and line named.
#include "check.hpp"
#include "deck/build_model.hpp"
#include "solver/static_analysis.hpp"

#include <cmath>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

using namespace calfit;

namespace {

const std::filesystem::path kDir = std::filesystem::temp_directory_path() / "calfit_test_garment";
const double kPi = std::acos(-1.0);
constexpr double kInner = 1.0, kTension = 1.0;

std::string number(double v) {
  std::ostringstream out;
  out << std::setprecision(17) << v;
  return out.str();
}

// A full ring between the circle of radius kInner (clamped) and the ellipse of semi-axes a, b (a circle when
// a = b), on a polar grid of nr x nt cells, each cut into two triangles; T6 mid-side nodes on the grid, so that
// every skin node lies on the ellipse (quadratic arcs), or with straight_skin those of the skin's faces at the
// middle of their chords.
struct Ring {
  int order = 1, nr = 3, nt = 48;
  double a = 2.0, b = 2.0;
  bool straight_skin = false;
  std::vector<std::pair<int, int>> skin;  // (element id, face 1..3), filled by deck()

  std::string deck(const std::string& loads_before_step, const std::string& step_loads) {
    const int rows = order * nr + 1, columns = order * nt;  // the seam theta = 2 pi is theta = 0
    auto id = [&](int i, int j) { return 1 + i * columns + (j % columns); };
    std::ostringstream d;
    d << "*NODE\n";
    for (int i = 0; i < rows; ++i)
      for (int j = 0; j < columns; ++j) {
        const double s = static_cast<double>(i) / (rows - 1);
        auto point = [&](int column) {
          const double t = 2.0 * kPi * column / columns;
          return Eigen::Vector2d((1 - s) * kInner * std::cos(t) + s * a * std::cos(t),
                                 (1 - s) * kInner * std::sin(t) + s * b * std::sin(t));
        };
        const bool chord_middle = straight_skin && order == 2 && i == rows - 1 && j % 2 == 1;
        const Eigen::Vector2d x = chord_middle ? Eigen::Vector2d(0.5 * (point(j - 1) + point(j + 1))) : point(j);
        d << id(i, j) << ", " << number(x.x()) << ", " << number(x.y()) << "\n";
      }
    d << "*ELEMENT, TYPE=" << (order == 1 ? "CPE3" : "CPE6") << ", ELSET=EALL\n";
    skin.clear();
    int element = 0;
    for (int i = 0; i < nr; ++i)
      for (int j = 0; j < nt; ++j) {
        const int p00[2] = {order * i, order * j}, p10[2] = {order * (i + 1), order * j},
                  p11[2] = {order * (i + 1), order * (j + 1)}, p01[2] = {order * i, order * (j + 1)};
        // counter-clockwise in (r, theta), and so in (x, y); face 2 of the first joins p10 to p11 (the skin's side)
        for (const auto& tri : {std::vector<const int*>{p00, p10, p11}, std::vector<const int*>{p00, p11, p01}}) {
          d << ++element;
          for (int k = 0; k < 3; ++k) d << ", " << id(tri[k][0], tri[k][1]);
          if (order == 2)
            for (int k = 0; k < 3; ++k)
              d << ", " << id((tri[k][0] + tri[(k + 1) % 3][0]) / 2, (tri[k][1] + tri[(k + 1) % 3][1]) / 2);
          d << "\n";
          if (i == nr - 1 && tri[1] == p10) skin.emplace_back(element, 2);
        }
      }
    d << "*NSET, NSET=INNER\n";
    for (int j = 0; j < columns; ++j) d << id(0, j) << "\n";
    d << "*NSET, NSET=OUTER\n";
    for (int j = 0; j < columns; ++j) d << id(rows - 1, j) << "\n";
    d << "*SURFACE, NAME=SKIN, TYPE=ELEMENT\n";
    for (const auto& [e, face] : skin) d << e << ", S" << face << "\n";
    d << "*MATERIAL, NAME=TISSUE\n*HYPERELASTIC, AVRIL\n1.0, 10.0\n*SOLID SECTION, ELSET=EALL, MATERIAL=TISSUE\n"
      << loads_before_step << "*BOUNDARY\nINNER, 1, 2\n*STEP, NLGEOM\n*STATIC\n0.5, 1.0\n" << step_loads << "*END STEP\n";
    return d.str();
  }

  std::string dload(double pressure) const {
    std::ostringstream d;
    d << "*DLOAD\n";
    for (const auto& [e, face] : skin) d << e << ", P" << face << ", " << number(pressure) << "\n";
    return d.str();
  }
};

std::string laplace(const std::string& extra) {
  return "*LAPLACE PRESSURE, SURFACE=SKIN, TENSION=" + number(kTension) + extra + "\n";
}

std::string write(const std::string& name, const std::string& text) {
  std::filesystem::create_directories(kDir);
  const std::filesystem::path p = kDir / name;
  std::ofstream(p) << text;
  return p.string();
}

// A model read from `text`, its one step solved; the analysis then evaluates residuals at the step's end.
struct Solved {
  Model model;
  StaticAnalysis analysis;
  Solved(const std::string& name, const std::string& text)
      : model(build_model(write(name + ".inp", text))), analysis(model, SolverSettings{}) {
    CHECK(analysis.run_step(0, [](const std::string&) {}).converged);
  }
};

double max_abs(const Eigen::VectorXd& v) { return v.cwiseAbs().maxCoeff(); }

// REFERENCE=1 against *DLOAD T / R0 on a circle: the largest difference of the external forces at u = 0 and at
// the solution, relative to the largest external force, and of the solutions, relative to max |u|.
struct CircleDifference {
  double force = 0.0, displacement = 0.0, pressure = 0.0;  // pressure: max |laplace_pressure - T/R0| / (T/R0)
};

CircleDifference circle_difference(int order, int nt, bool straight_skin = false) {
  Ring ring;
  ring.order = order;
  ring.nt = nt;
  ring.straight_skin = straight_skin;
  const std::string label = "circle-t" + std::to_string(order == 1 ? 3 : 6) + (straight_skin ? "-straight-" : "-") +
                            std::to_string(nt);
  const double p = kTension / ring.a;
  Solved reference(label + "-reference", ring.deck("", laplace(", REFERENCE=1")));
  Solved follower(label + "-dload", ring.deck("", ring.dload(p)));
  Solved unloaded(label + "-unloaded", ring.deck("", "*LAPLACE PRESSURE, SURFACE=SKIN, TENSION=0\n"));
  const Eigen::VectorXd& u = reference.analysis.solution();
  CircleDifference out;
  for (const Eigen::VectorXd& at : {Eigen::VectorXd(Eigen::VectorXd::Zero(u.size())), u}) {
    const Eigen::VectorXd f_ext = unloaded.analysis.residual(at) - follower.analysis.residual(at);
    const Eigen::VectorXd difference = reference.analysis.residual(at) - follower.analysis.residual(at);
    out.force = std::max(out.force, max_abs(difference) / max_abs(f_ext));
  }
  out.displacement = max_abs(u - follower.analysis.solution()) / max_abs(u);
  const FieldOutput fields = reference.analysis.output();
  for (int node : reference.model.node_sets.at("OUTER"))
    out.pressure = std::max(out.pressure, std::abs(fields.laplace_pressure[node] - p) / p);
  std::cout << label << ": REFERENCE=1 vs *DLOAD T/R0, external force " << out.force << ", displacement "
            << out.displacement << " (max |u| " << max_abs(u) << "), laplace_pressure " << out.pressure << '\n';
  return out;
}

void circle_tests() {
  for (const CircleDifference& exact : {circle_difference(1, 48), circle_difference(2, 32, true)}) {
    CHECK(exact.force < 1e-12);
    CHECK(exact.displacement < 1e-10);
    CHECK(exact.pressure < 1e-12);
  }
  // Quadratic arcs: the mean unit tangent of an arc is shorter than 1, and p0 is T / R0 to second order.
  const CircleDifference coarse = circle_difference(2, 16), fine = circle_difference(2, 64);
  CHECK(fine.force < coarse.force / 12.0);
  CHECK(fine.displacement < coarse.displacement / 12.0);
  CHECK(fine.pressure < 1e-3);
  CHECK(fine.displacement < 1e-3);
}

// The load is affine in alpha, and REFERENCE=0 is the deck without it.
void affine_in_alpha_tests(int order) {
  Ring ring;
  ring.order = order;
  ring.nt = order == 1 ? 48 : 24;
  ring.a = 2.4;
  ring.b = 1.6;
  const std::string profile = "*TENSION PROFILE, NAME=GARMENT, TYPE=FOURIER\n1, 0.2, -0.1\n2, 0.1, 0.05\n";
  const std::string label = "ellipse-t" + std::to_string(order == 1 ? 3 : 6);
  auto solved = [&](const std::string& name, const std::string& extra) {
    return std::make_unique<Solved>(label + "-" + name, ring.deck(profile, laplace(", PROFILE=GARMENT" + extra)));
  };
  const auto mixed = solved("alpha-0.3", ", REFERENCE=0.3");
  const auto deformed = solved("alpha-0", ", REFERENCE=0"), plain = solved("plain", "");
  const auto reference = solved("alpha-1", ", REFERENCE=1");
  const Eigen::VectorXd& u = mixed->analysis.solution();
  const Eigen::VectorXd R0 = deformed->analysis.residual(u), R1 = reference->analysis.residual(u);
  const Eigen::VectorXd combined = 0.7 * R0 + 0.3 * R1;
  const double scale = max_abs(R1 - R0);
  const double error = max_abs(mixed->analysis.residual(u) - combined) / scale;
  std::cout << label << ": R(0.3) vs 0.7 R(0) + 0.3 R(1), relative " << error << "; max |R(1) - R(0)| " << scale << '\n';
  CHECK(scale > 0.0);
  CHECK(error < 1e-12);
  CHECK(plain->analysis.residual(u) == R0);
  CHECK(plain->analysis.solution() == deformed->analysis.solution());
  // The two laws differ on a non-circular outline: the deformed one follows the deformed contour.
  CHECK(max_abs(reference->analysis.solution() - deformed->analysis.solution()) > 1e-3 * max_abs(u));
}

void deck_error_tests() {
  Ring ring;
  ring.nt = 8;
  ring.nr = 1;
  for (const auto& [value, fragment] : std::vector<std::pair<std::string, std::string>>{
           {"1.5", "outside [0, 1]"}, {"-0.1", "outside [0, 1]"}, {"half", "REFERENCE is not a number: 'half'"},
           {"nan", "REFERENCE is not a number"}, {"", "REFERENCE= has no value"}}) {
    const std::string text = ring.deck("", laplace(", REFERENCE=" + value));
    std::istringstream lines(text);
    std::string line;
    int number_of_line = 0, keyword_line = 0;
    while (std::getline(lines, line)) {
      ++number_of_line;
      if (line.rfind("*LAPLACE PRESSURE", 0) == 0) keyword_line = number_of_line;
    }
    std::string message;
    try {
      build_model(write("bad-reference.inp", text));
    } catch (const DeckError& e) {
      message = e.what();
    }
    std::cout << "REFERENCE=" << value << ": " << message << '\n';
    CHECK(message.find("bad-reference.inp:" + std::to_string(keyword_line) + ":") != std::string::npos);
    CHECK(message.find(fragment) != std::string::npos);
  }
}

}  // namespace

int main() {
  circle_tests();
  affine_in_alpha_tests(1);
  affine_in_alpha_tests(2);
  deck_error_tests();
  return calfit::testing::tally().finish();
}
