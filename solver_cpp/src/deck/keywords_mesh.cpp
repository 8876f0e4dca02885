// Deck keywords -> Model: the mesh, its sets and surfaces (*NODE, *ELEMENT, *NSET, *ELSET, *SURFACE;
// solver_cpp/README.md, Standard keywords) and the geometry checks of its elements (inverted, degenerate, distorted).
#include "deck/model_builder.hpp"
#include "element/solid_element.hpp"

#include <algorithm>
#include <set>
#include <string>

namespace calfit::deck_building {

namespace {

// Checks det(dX/dxi) of a T6 at its nodes and the 6-point rule, which covers the
// places where a misplaced mid-side node makes the map fold.
struct SolidElementProbe {
  double min_jacobian(const NodeMatrix& X) const {
    static const double probes[][2] = {{0, 0},   {1, 0},   {0, 1},   {0.5, 0},   {0.5, 0.5}, {0, 0.5},
                                       {1. / 3, 1. / 3}, {0.1, 0.1}, {0.8, 0.1}, {0.1, 0.8}};
    Eigen::VectorXd N;
    Eigen::MatrixXd dN;
    double smallest = 1e300;
    for (const auto& p : probes) {
      shape_functions(ElementShape::T6, p[0], p[1], N, dN);
      smallest = std::min(smallest, (X.transpose() * dN).determinant());
    }
    return smallest;
  }
};

}  // namespace

void ModelBuilder::node(const KeywordBlock& b) {
  b.allow_only({"NSET"});
  model_data(b);
  needs_data(b);
  const std::optional<std::string> set = b.value("NSET");
  for (const DataLine& line : b.data) {
    field_count(line, 3, 4, "*NODE data line (id, x, y[, z])");
    Context c{line};
    const int id = c.integer(0, "node number");
    if (id <= 0) throw DeckError(line.where, "node number must be positive, found " + std::to_string(id));
    if (model_.node_index.count(id)) throw DeckError(line.where, "node " + std::to_string(id) + " is defined twice");
    const int index = static_cast<int>(model_.coordinates.size());
    model_.node_index[id] = index;
    model_.node_ids.push_back(id);
    model_.coordinates.emplace_back(c.number(1, "x coordinate"), c.number(2, "y coordinate"));
    if (c.field_count() == 4) c.number(3, "z coordinate");
    if (set) model_.node_sets[upper(*set)].push_back(index);
  }
}

void ModelBuilder::element(const KeywordBlock& b) {
  b.allow_only({"TYPE", "ELSET"});
  model_data(b);
  needs_data(b);
  const std::string type = upper(b.required("TYPE"));
  ElementShape shape;
  if (type == "CPE3" || type == "CPE3H") {
    shape = ElementShape::T3;
  } else if (type == "CPE6" || type == "CPE6H") {
    shape = ElementShape::T6;
  } else {
    throw DeckError(b.where, "unknown element type " + type +
                                 ": calfit-fe is plane strain (TYPE=CPE3, CPE6, or the hybrid CPE3H, CPE6H)");
  }
  const bool hybrid = type.back() == 'H';
  const std::size_t n = static_cast<std::size_t>(node_count(shape));
  const std::optional<std::string> set = b.value("ELSET");
  for (const DataLine& line : b.data) {
    field_count(line, n + 1, n + 1, "*ELEMENT, TYPE=" + type + " data line (id and " + std::to_string(n) + " nodes)");
    Context c{line};
    ElementDef e;
    e.id = c.integer(0, "element number");
    if (e.id <= 0) throw DeckError(line.where, "element number must be positive");
    if (model_.element_index.count(e.id))
      throw DeckError(line.where, "element " + std::to_string(e.id) + " is defined twice");
    e.shape = shape;
    e.type = type;
    e.hybrid = hybrid;
    e.where = line.where;
    for (std::size_t k = 1; k <= n; ++k) e.nodes.push_back(node(line.fields[k], line.where));
    if (std::set<int>(e.nodes.begin(), e.nodes.end()).size() != n)
      throw DeckError(line.where, "element " + std::to_string(e.id) + " lists the same node twice");
    const int index = static_cast<int>(model_.elements.size());
    model_.element_index[e.id] = index;
    model_.elements.push_back(std::move(e));
    if (set) model_.element_sets[upper(*set)].push_back(index);
  }
}

template <typename Resolve>
void ModelBuilder::fill_set(const KeywordBlock& b, std::vector<int>& target, Resolve resolve, const std::string& item) {
  needs_data(b);
  for (const DataLine& line : b.data) {
    if (b.flag("GENERATE")) {
      field_count(line, 2, 3, "GENERATE data line (first, last[, increment])");
      Context c{line};
      const int first = c.integer(0, "first " + item), last = c.integer(1, "last " + item);
      const int step = c.field_count() == 3 ? c.integer(2, "increment") : 1;
      if (step <= 0 || last < first) throw DeckError(line.where, "GENERATE needs first <= last and a positive increment");
      for (int id = first; id <= last; id += step) {
        const std::vector<int> found = resolve(std::to_string(id), line.where);
        target.insert(target.end(), found.begin(), found.end());
      }
      continue;
    }
    for (const std::string& f : line.fields) {
      if (f.empty()) continue;
      const std::vector<int> found = resolve(f, line.where);
      target.insert(target.end(), found.begin(), found.end());
    }
  }
}

void ModelBuilder::node_set(const KeywordBlock& b) {
  b.allow_only({"NSET", "GENERATE"});
  model_data(b);
  std::vector<int>& target = model_.node_sets[upper(b.required("NSET"))];
  fill_set(b, target, [this](const std::string& t, const SourceLocation& w) { return nodes_of(t, w); }, "node");
}

void ModelBuilder::element_set(const KeywordBlock& b) {
  b.allow_only({"ELSET", "GENERATE"});
  model_data(b);
  std::vector<int>& target = model_.element_sets[upper(b.required("ELSET"))];
  fill_set(b, target, [this](const std::string& t, const SourceLocation& w) { return elements_of(t, w); }, "element");
}

void ModelBuilder::surface(const KeywordBlock& b) {
  b.allow_only({"NAME", "TYPE"});
  model_data(b);
  needs_data(b);
  const std::string type = upper(b.value("TYPE").value_or("ELEMENT"));
  if (type != "ELEMENT") throw DeckError(b.where, "*SURFACE, TYPE=" + type + " is not supported: use TYPE=ELEMENT");
  const std::string name = upper(b.required("NAME"));
  if (model_.surface(name) >= 0) throw DeckError(b.where, "surface " + name + " is defined twice");
  std::vector<Face> faces;
  for (const DataLine& line : b.data) {
    field_count(line, 2, 2, "*SURFACE data line (element or element set, face S1..S3)");
    const int face = face_label(line.fields[1], "S", line.where);
    for (int e : elements_of(line.fields[0], line.where)) faces.push_back({e, face});
  }
  model_.surface_names.push_back(name);
  model_.surfaces.push_back(std::move(faces));
}

void ModelBuilder::check_geometry(const ElementDef& e) const {
  NodeMatrix X(node_count(e.shape), 2);
  for (int k = 0; k < X.rows(); ++k) X.row(k) = model_.coordinates[e.nodes[k]].transpose();
  // Corner area and scale: a clockwise element is inverted, a flat one degenerate.
  const Eigen::Vector2d a = X.row(1) - X.row(0), c = X.row(2) - X.row(0);
  const double area = 0.5 * (a.x() * c.y() - a.y() * c.x());
  const double scale = std::max({a.squaredNorm(), c.squaredNorm(), (X.row(2) - X.row(1)).squaredNorm()});
  const std::string id = std::to_string(e.id);
  if (std::abs(area) <= 1e-10 * scale || scale == 0.0)
    throw DeckError(e.where, "element " + id + " is degenerate (zero area): its corner nodes are collinear or coincide");
  if (area < 0.0)
    throw DeckError(e.where, "element " + id + " is inverted (nodes listed clockwise): list its corners counter-clockwise");
  if (e.shape == ElementShape::T6) {
    // Mid-side nodes far from their edge make det(dX/dxi) change sign inside.
    static const SolidElementProbe probe;
    if (probe.min_jacobian(X) <= 0.0)
      throw DeckError(e.where, "element " + id + " is distorted: a mid-side node lies too far from its edge's midpoint");
  }
}

}  // namespace calfit::deck_building
