// Deck keywords -> Model: the project's kinematics of a step (*VOLUME CHANGE, *AXIAL STRETCH, *RIGID MOTION;
// solver_cpp/README.md, Volume change, axial stretch and rigid motion).
#include "deck/model_builder.hpp"

#include <algorithm>
#include <string>
#include <utility>

namespace calfit::deck_building {

// The one data line of a keyword that takes exactly `count` values.
const DataLine& ModelBuilder::one_data_line(const KeywordBlock& b, std::size_t count, const std::string& what) {
  needs_data(b);
  if (b.data.size() > 1) throw DeckError(b.data[1].where, "*" + b.name + " takes one data line (" + what + ")");
  field_count(b.data[0], count, count, "*" + b.name + " data line (" + what + ")");
  return b.data[0];
}

void ModelBuilder::volume_change(const KeywordBlock& b) {
  b.allow_only({"ELSET", "OP"});
  step_data(b);
  apply_op(b, loads_.volume_change);
  const std::vector<int> elements = elements_of(b.required("ELSET"), b.where);
  const DataLine& line = one_data_line(b, 1, "dv, the relative volume change of the stress-free state");
  const double dv = Context{line}.number(0, "dv");
  require(dv > -1.0, line,
          "dv must be > -1: the stress-free volume becomes (1 + dv) times the reference volume "
          "(e.g. -0.05 for a 5% fluid loss)");
  for (int e : elements) loads_.volume_change[e] = dv;
}

void ModelBuilder::axial_stretch(const KeywordBlock& b) {
  b.allow_only({});
  step_data(b);
  const DataLine& line = one_data_line(b, 1, "lambda_z, the out-of-plane stretch F33");
  const double stretch = Context{line}.number(0, "lambda_z");
  require(stretch > 0.0, line, "lambda_z must be > 0 (1 is plane strain, e.g. 0.98 for a 2% axial shortening)");
  loads_.axial_stretch = stretch;
}

void ModelBuilder::rigid_motion(const KeywordBlock& b) {
  b.allow_only({"NSET", "CX", "CY", "OP"});
  step_data(b);
  apply_op(b, loads_.rigid_motions);
  RigidMotion motion;
  motion.where = b.where;
  motion.node_set = upper(b.required("NSET"));
  motion.nodes = nodes_of(b.required("NSET"), b.where);
  std::sort(motion.nodes.begin(), motion.nodes.end());  // sorted, once each: binary_search below
  motion.nodes.erase(std::unique(motion.nodes.begin(), motion.nodes.end()), motion.nodes.end());
  const auto cx = b.value("CX"), cy = b.value("CY");
  if (cx.has_value() != cy.has_value()) throw DeckError(b.where, "give both CX= and CY= (or neither: the set's centroid)");
  if (cx) {
    motion.center = {to_double(*cx, b.where, "CX"), to_double(*cy, b.where, "CY")};
  } else {
    for (int n : motion.nodes) motion.center += model_.coordinates[n];
    motion.center /= static_cast<double>(motion.nodes.size());
  }
  const DataLine& line = one_data_line(b, 3, "ux, uy, angle in degrees");
  Context c{line};
  motion.ux = c.number(0, "ux");
  motion.uy = c.number(1, "uy");
  motion.angle_degrees = c.number(2, "angle");
  for (const auto& [name, other] : loads_.rigid_motions) {
    if (name == motion.node_set) continue;  // OP=MOD: this set's motion is replaced
    for (int n : motion.nodes)
      if (std::binary_search(other.nodes.begin(), other.nodes.end(), n))
        throw DeckError(b.where, "node " + std::to_string(model_.node_ids[n]) + " of set " + motion.node_set +
                                     " is already moved by *RIGID MOTION, NSET=" + name + " (line " +
                                     std::to_string(other.where.line) + "): a node follows one rigid motion; split the sets or use OP=NEW");
  }
  // The motion prescribes both dofs of its nodes: it takes over from a *BOUNDARY on them
  // (a bone clamped in the model data, then moved).
  for (int n : motion.nodes) {
    loads_.prescribed.erase(2 * n);
    loads_.prescribed.erase(2 * n + 1);
  }
  loads_.rigid_motions[motion.node_set] = std::move(motion);
}

// A *BOUNDARY inside a step may not prescribe a node that a rigid motion drives.
void ModelBuilder::check_not_rigid(int node, const SourceLocation& where) const {
  for (const auto& [name, motion] : loads_.rigid_motions)
    if (std::binary_search(motion.nodes.begin(), motion.nodes.end(), node))
      throw DeckError(where, "node " + std::to_string(model_.node_ids[node]) + " is moved by *RIGID MOTION, NSET=" +
                                 name + " (line " + std::to_string(motion.where.line) +
                                 "): remove it from that set, or remove the motion with *RIGID MOTION, OP=NEW");
}

}  // namespace calfit::deck_building
