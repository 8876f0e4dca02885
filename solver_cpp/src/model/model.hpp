// The finite-element model that the deck parser yields and the solver consumes:
// mesh, sets, surfaces, materials, sections and the load history of each step.
// Indices are 0-based positions in the vectors; ids are the deck's numbers.
#pragma once

#include "contact/node_to_segment.hpp"
#include "deck/deck_reader.hpp"
#include "element/triangle.hpp"
#include "material/material.hpp"

#include <Eigen/Dense>
#include <map>
#include <memory>
#include <string>
#include <unordered_map>
#include <utility>
#include <vector>

namespace calfit {

struct ElementDef {
  int id = 0;
  ElementShape shape = ElementShape::T3;
  std::string type;          // as in the deck: CPE3, CPE6, CPE3H, CPE6H
  bool hybrid = false;       // mixed u/p (the H types)
  std::vector<int> nodes;    // node indices
  int section = -1;
  SourceLocation where;      // the element's data line
};

struct MaterialDef {
  std::string name;
  std::shared_ptr<const Material> law;
  SourceLocation where;
};

struct SectionDef {
  int material = -1;
  double thickness = 1.0;
  int quadrature_degree = 2;  // per element shape, resolved when elements are built
  bool full_integration = false;
  SourceLocation where;
};

struct Face {
  int element = 0;  // element index
  int face = 0;     // 0..2: corner face -> corner face+1
};

struct TensionProfile {
  std::string name;
  bool has_center = false;
  Eigen::Vector2d center = Eigen::Vector2d::Zero();
  std::vector<std::pair<double, double>> angle_factor;  // degrees in [0, 360), sorted
  SourceLocation where;
  // Periodic linear interpolation of the factor at polar angle theta (degrees).
  double factor(double theta_degrees) const;
};

struct InteractionDef {
  std::string name;
  ContactLaw law;
  bool has_behavior = false;
  SourceLocation where;
};

// Penalty contact between the nodes of a slave surface and the faces of a master
// surface (*CONTACT PAIR); active in the steps where `active` says so (*MODEL CHANGE).
struct ContactPairDef {
  int slave = -1, master = -1;  // surface indices
  int interaction = -1;
  SourceLocation where;
};

struct LaplaceLoad {
  double tension = 0.0;  // force per unit length
  int profile = -1;      // index into Model::profiles, -1 for constant tension
};

// *RIGID MOTION: both dofs of every node of a set follow u = t + (R(angle) - I)(X - center),
// X the node's reference position. t and the angle are ramped over the step (the angle
// itself, so that a large rotation stays rigid at every increment).
struct RigidMotion {
  std::string node_set;  // upper-case set name, the key in LoadState::rigid_motions
  std::vector<int> nodes;  // node indices
  Eigen::Vector2d center = Eigen::Vector2d::Zero();  // CX, CY or the centroid of the nodes' reference positions
  double ux = 0.0, uy = 0.0;  // translation t
  double angle_degrees = 0.0;  // counter-clockwise
  SourceLocation where;

  static Eigen::Vector2d displacement(const Eigen::Vector2d& translation, double angle_degrees,
                                      const Eigen::Vector2d& center, const Eigen::Vector2d& X) {
    const Eigen::Matrix2d R = Eigen::Rotation2Dd(angle_degrees * 3.14159265358979323846 / 180.0).toRotationMatrix();
    return translation + (R - Eigen::Matrix2d::Identity()) * (X - center);
  }
  Eigen::Vector2d displacement(const Eigen::Vector2d& X) const {
    return displacement({ux, uy}, angle_degrees, center, X);
  }
};

// Loads, prescribed displacements and imposed kinematics in force at the end of a step.
// Each step ramps linearly from the previous step's state to its own; before the first
// step every value is zero, except axial_stretch = 1. The values are plain data: a
// model copy may change them (e.g. to differentiate the solution with respect to them).
struct LoadState {
  std::map<int, double> prescribed;               // dof -> value (dof = 2 node + component)
  std::map<int, double> forces;                   // dof -> concentrated force
  std::map<std::pair<int, int>, double> pressures;  // (element, face) -> follower pressure
  std::map<int, LaplaceLoad> laplace;             // surface index -> garment tension
  std::vector<char> contact_active;               // per contact pair
  // *VOLUME CHANGE: element index -> dv, the relative volume change of the element's
  // stress-free state (growth F_g = (1 + dv)^(1/3) I; dv < 0 for drainage).
  std::map<int, double> volume_change;
  // *AXIAL STRETCH: lambda_z = F33 of every element (generalized plane strain).
  double axial_stretch = 1.0;
  // *RIGID MOTION: node-set name -> motion; these nodes' dofs are prescribed by it.
  std::map<std::string, RigidMotion> rigid_motions;
};

struct StepDef {
  SourceLocation where;
  int max_increments = 100;
  double initial_dt = 1.0, period = 1.0, min_dt = 1e-5, max_dt = 1.0;
  LoadState loads;
};

struct Model {
  std::string deck_path;
  std::vector<int> node_ids;
  std::vector<Eigen::Vector2d> coordinates;
  std::unordered_map<int, int> node_index;  // id -> index
  std::vector<ElementDef> elements;
  std::unordered_map<int, int> element_index;
  std::map<std::string, std::vector<int>> node_sets;     // upper-case name -> node indices
  std::map<std::string, std::vector<int>> element_sets;  // upper-case name -> element indices
  std::vector<std::string> surface_names;
  std::vector<std::vector<Face>> surfaces;
  std::vector<MaterialDef> materials;
  std::vector<SectionDef> sections;
  std::vector<TensionProfile> profiles;
  std::vector<InteractionDef> interactions;
  std::vector<ContactPairDef> contact_pairs;
  std::vector<StepDef> steps;

  int dof_count() const { return 2 * static_cast<int>(coordinates.size()); }
  int surface(const std::string& name) const;  // -1 when unknown
};

// Parses the deck at `path` and checks the mesh; throws DeckError on bad input.
Model build_model(const std::string& path);

}  // namespace calfit
