// Deck reader unit tests: keyword/parameter parsing, continuation lines, *INCLUDE with
// the included file's own line numbers, GENERATE sets, OP=NEW, and errors that name
// the file and line.
#include "check.hpp"
#include "model/model.hpp"

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

  const std::string unknown = write("unknown.inp", "*NODE\n1, 0, 0\n*FOO, BAR=1\n");
  CHECK(error_of(unknown).find("unknown.inp:3: unknown keyword *FOO") != std::string::npos);
  const std::string number = write("number.inp", "*NODE\n1, 0, 0x\n");
  CHECK(error_of(number).find("number.inp:2: y coordinate is not a number") != std::string::npos);
  return calfit::testing::tally().finish();
}
