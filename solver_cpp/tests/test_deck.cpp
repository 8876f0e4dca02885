// Deck reader unit tests: keyword/parameter parsing, continuation lines, *INCLUDE with
// the included file's own line numbers, GENERATE sets, OP=NEW, *HYPERELASTIC, POLYNOMIAL
// (two data lines for N = 3), and errors that name the file and line.
#include "check.hpp"
#include "deck/build_model.hpp"

#include <filesystem>
#include <fstream>

using namespace calfit;

namespace {

const std::filesystem::path kDir = std::filesystem::temp_directory_path() / "calfit_test_deck";

std::string write(const std::string& name, const std::string& text) {
  std::filesystem::create_directories(kDir);
  const std::filesystem::path p = kDir / name;
  std::ofstream(p) << text;
  return p.string();
}

const char* kMesh =
    "*NODE, NSET=ALL\n1, 0, 0\n2, 1, 0\n3, 1, 1\n4, 0, 1\n"
    "*ELEMENT, TYPE=CPE3,\n ELSET=E\n1, 1, 2, 3\n2, 1, 3, 4\n"
    "*NSET, NSET=GEN, GENERATE\n1, 4, 3\n";

std::string error_of(const std::string& deck) {
  try {
    build_model(deck);
  } catch (const DeckError& e) {
    return e.what();
  }
  return "";
}

}  // namespace

int main() {
  const std::string mesh = write("mesh.inp", kMesh);
  const std::string deck = write("ok.inp",
                                 "** comment\n*HEADING\nunit square\n*INCLUDE, INPUT=mesh.inp\n"
                                 "*MATERIAL, NAME=m\n*Hyperelastic, neo hooke\n1.0, 0.1\n"
                                 "*SOLID SECTION, ELSET=e, MATERIAL=M\n*BOUNDARY\n1, 1, 2\n"
                                 "*STEP, NLGEOM, INC=50\n*STATIC\n0.5, 1.0\n*CLOAD\n3, 1, 0.1\n*END STEP\n"
                                 "*STEP, NLGEOM\n*STATIC\n*CLOAD, OP=NEW\n4, 2, 0.2\n*END STEP\n");
  const Model model = build_model(deck);
  CHECK(model.coordinates.size() == 4);
  CHECK(model.elements.size() == 2);
  CHECK(model.element_sets.at("E").size() == 2);                   // continued keyword line
  CHECK(model.node_sets.at("GEN") == std::vector<int>({0, 3}));    // GENERATE 1, 4, 3
  CHECK(model.steps.size() == 2);
  CHECK(model.steps[0].max_increments == 50);
  CHECK(model.steps[0].initial_dt == 0.5);
  CHECK(model.steps[0].loads.prescribed.size() == 2);              // model-level *BOUNDARY carried
  CHECK(model.steps[0].loads.forces.count(2 * 2) == 1);
  CHECK(model.steps[1].loads.forces.size() == 1 && model.steps[1].loads.forces.count(2 * 3 + 1) == 1);  // OP=NEW

  // An error inside an included file names that file and its own line.
  write("bad_mesh.inp", "*NODE\n1, 0, 0\n2, 1, 0\n3, 1, 1\n*ELEMENT, TYPE=CPE3, ELSET=E\n1, 1, 2, 9\n");
  const std::string bad = write("bad.inp", "*HEADING\n*INCLUDE, INPUT=bad_mesh.inp\n");
  const std::string message = error_of(bad);
  std::cout << message << '\n';
  CHECK(message.find("bad_mesh.inp:6:") != std::string::npos);
  CHECK(message.find("node 9") != std::string::npos);

  // Project kinematics: values kept per step, OP=NEW, the rigid motion's default centre
  // (the centroid of its nodes) and its take-over of a model-level *BOUNDARY.
  const std::string kinematics = write(
      "kinematics.inp",
      "*INCLUDE, INPUT=mesh.inp\n*NSET, NSET=LEFT\n1, 4\n"
      "*MATERIAL, NAME=m\n*HYPERELASTIC, AVRIL\n1.0, 10.0, 0.25\n*SOLID SECTION, ELSET=E, MATERIAL=M\n"
      "*BOUNDARY\nLEFT, 1, 2\n3, 2\n"
      "*STEP, NLGEOM\n*STATIC\n*VOLUME CHANGE, ELSET=E\n-0.1\n*AXIAL STRETCH\n0.95\n"
      "*RIGID MOTION, NSET=LEFT\n0.1, -0.2, 30\n*END STEP\n"
      "*STEP, NLGEOM\n*STATIC\n*VOLUME CHANGE, ELSET=1, OP=NEW\n0.05\n"
      "*RIGID MOTION, NSET=LEFT, CX=2, CY=3\n0, 0, -10\n*END STEP\n");
  const Model k = build_model(kinematics);
  const LoadState& k1 = k.steps[0].loads;
  const LoadState& k2 = k.steps[1].loads;
  CHECK(k1.volume_change.size() == 2 && k1.volume_change.at(0) == -0.1 && k1.volume_change.at(1) == -0.1);
  CHECK(k2.volume_change.size() == 1 && k2.volume_change.at(0) == 0.05);  // OP=NEW dropped element 2
  CHECK(k1.axial_stretch == 0.95 && k2.axial_stretch == 0.95);            // carried to the next step
  CHECK(k1.rigid_motions.count("LEFT") == 1);
  const RigidMotion& left = k1.rigid_motions.at("LEFT");
  CHECK(left.nodes == std::vector<int>({0, 3}));
  CHECK_NEAR(left.center.x(), 0.0, 1e-15);
  CHECK_NEAR(left.center.y(), 0.5, 1e-15);
  CHECK(left.ux == 0.1 && left.uy == -0.2 && left.angle_degrees == 30.0);
  CHECK(k1.prescribed.size() == 1 && k1.prescribed.count(2 * 2 + 1) == 1);  // LEFT's zero BCs taken over
  CHECK(k2.rigid_motions.at("LEFT").center == Eigen::Vector2d(2.0, 3.0));
  // u = t + (R - I)(X - c): a quarter turn about (1, 0) takes (2, 0) to (1, 1).
  RigidMotion quarter;
  quarter.center = {1.0, 0.0};
  quarter.angle_degrees = 90.0;
  quarter.ux = 0.5;
  const Eigen::Vector2d d = quarter.displacement(Eigen::Vector2d(2.0, 0.0));
  CHECK_NEAR(d.x(), -0.5, 1e-15);
  CHECK_NEAR(d.y(), 1.0, 1e-15);
  // A *BOUNDARY in a step on a rigidly moved node names the motion's line.
  const std::string conflict = write("conflict.inp",
                                     "*INCLUDE, INPUT=mesh.inp\n*NSET, NSET=LEFT\n1, 4\n*MATERIAL, NAME=m\n"
                                     "*HYPERELASTIC, AVRIL\n1.0, 10.0\n*SOLID SECTION, ELSET=E, MATERIAL=M\n"
                                     "*STEP, NLGEOM\n*RIGID MOTION, NSET=LEFT\n0, 0, 5\n*BOUNDARY\n4, 1, 1, 0.1\n*END STEP\n");
  const std::string conflict_message = error_of(conflict);
  std::cout << conflict_message << '\n';
  CHECK(conflict_message.find("conflict.inp:12:") != std::string::npos);
  CHECK(conflict_message.find("(line 9)") != std::string::npos);

  // *HYPERELASTIC, POLYNOMIAL: CalculiX's order and, for N = 3, its two data lines (8 constants, then 4).
  auto polynomial = [&](const std::string& name, const std::string& law_lines) {
    return write(name, "*INCLUDE, INPUT=mesh.inp\n*MATERIAL, NAME=m\n" + law_lines +
                           "*SOLID SECTION, ELSET=E, MATERIAL=M\n*STEP, NLGEOM\n*STATIC\n*END STEP\n");
  };
  const Model p3 = build_model(polynomial("poly3.inp", "*HYPERELASTIC, POLYNOMIAL, N=3\n"
                                                       "0.8, 0.3, -0.04, 0.05, 0.02, 0.01, -0.03, 0.015\n"
                                                       "0.006, 0.1, 0.5, 2.0\n"));
  const LawConstants& c3 = p3.materials[0].constants;
  CHECK(c3.law == "POLYNOMIAL" && c3.values.size() == 12);
  CHECK(c3.values[c3.index("C20")] == -0.04 && c3.values[c3.index("C03")] == 0.006 && c3.values[c3.index("D3")] == 2.0);
  // D1 = 0 is the incompressible law, as for MOONEY-RIVLIN: the displacement elements refuse it.
  CHECK(error_of(polynomial("poly2.inp", "*HYPERELASTIC, POLYNOMIAL, N=2\n1, 0.1, -0.04, 0, 0, 0, 0\n"))
            .find("is incompressible (D = 0)") != std::string::npos);
  const std::string wrong_count = error_of(polynomial("poly_count.inp", "*HYPERELASTIC, POLYNOMIAL, N=2\n1, 0.1, 0.1\n"));
  std::cout << wrong_count << '\n';
  CHECK(wrong_count.find("poly_count.inp:4:") != std::string::npos);
  CHECK(wrong_count.find("C10, C01, C20, C11, C02, D1, D2): expected 7 values, found 3") != std::string::npos);
  const std::string one_line = error_of(polynomial("poly_one_line.inp", "*HYPERELASTIC, POLYNOMIAL, N=3\n"
                                                                        "1, 0, 0, 0, 0, 0, 0, 0, 0, 0.1, 0, 0\n"));
  std::cout << one_line << '\n';
  CHECK(one_line.find("poly_one_line.inp:4:") != std::string::npos && one_line.find("2 data lines") != std::string::npos);
  const std::string short_first = error_of(polynomial("poly_short.inp", "*HYPERELASTIC, POLYNOMIAL, N=3\n"
                                                                        "1, 0, 0, 0, 0, 0, 0\n0, 0, 0.1, 0, 0\n"));
  std::cout << short_first << '\n';
  CHECK(short_first.find("poly_short.inp:4:") != std::string::npos &&
        short_first.find("expected 8 values, found 7") != std::string::npos);
  const std::string soft = error_of(polynomial("poly_soft.inp", "*HYPERELASTIC, POLYNOMIAL, N=1\n0.1, -0.2, 0.1\n"));
  CHECK(soft.find("poly_soft.inp:4: C10 + C01") != std::string::npos);
  const std::string negative_d = error_of(polynomial("poly_d.inp", "*HYPERELASTIC, POLYNOMIAL, N=3\n"
                                                                   "1, 0, 0, 0, 0, 0, 0, 0\n0, 0.1, -1, 0\n"));
  CHECK(negative_d.find("poly_d.inp:5: D2 must be >= 0") != std::string::npos);
  CHECK(error_of(polynomial("poly_n.inp", "*HYPERELASTIC, POLYNOMIAL, N=4\n1, 0, 0.1\n")).find("N = 1, 2 or 3") !=
        std::string::npos);

  const std::string unknown = write("unknown.inp", "*NODE\n1, 0, 0\n*FOO, BAR=1\n");
  CHECK(error_of(unknown).find("unknown.inp:3: unknown keyword *FOO") != std::string::npos);
  const std::string number = write("number.inp", "*NODE\n1, 0, 0x\n");
  CHECK(error_of(number).find("number.inp:2: y coordinate is not a number") != std::string::npos);
  return calfit::testing::tally().finish();
}
