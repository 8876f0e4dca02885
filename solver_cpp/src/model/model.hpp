// The finite-element model that the deck parser yields and the solver consumes:
// mesh, sets, surfaces, materials, sections and the load history of each step.
// Indices are 0-based positions in the vectors; ids are the deck's numbers.
#pragma once

#include "contact/node_to_segment.hpp"
#include "element/triangle.hpp"
#include "material/laws.hpp"
#include "material/material.hpp"
#include "model/source_location.hpp"

#include <Eigen/Dense>
#include <functional>
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
  LawConstants constants;  // what `law` was built from
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

// Garment tension factor around a surface: T(theta) = TENSION x factor(theta), theta the
// polar angle of a node's reference position about the centre (default: the surface's
// node centroid).
//   TYPE=TABLE:   periodic linear interpolation of (angle, factor) pairs;
//   TYPE=FOURIER: factor = 1 + sum_k (a_k cos k theta + b_k sin k theta), k >= 1.
struct TensionProfile {
  enum class Type { Table, Fourier };
  std::string name;
  Type type = Type::Table;
  bool has_center = false;
  Eigen::Vector2d center = Eigen::Vector2d::Zero();
  std::vector<std::pair<double, double>> angle_factor;  // TABLE: degrees in [0, 360), sorted
  std::map<int, std::pair<double, double>> harmonics;   // FOURIER: k -> (a_k, b_k)
  SourceLocation where;
  double factor(double theta_degrees) const;
  // FOURIER: the smallest factor around the circle (dense sampling refined by golden
  // section; a trigonometric polynomial of degree k_max has at most 2 k_max extrema).
  double minimum_factor(double* at_degrees = nullptr) const;
};

struct InteractionDef {
  std::string name;
  ContactLaw law;
  bool has_behavior = false;
  SourceLocation where;
};

// *GAP PROFILE: the nodes of a contact pair's slave surface stand out from their mesh positions,
// as the contact sees them, by delta(theta) = sum_k a_k cos k theta + b_k sin k theta (mm) along the
// master's normal, theta the polar angle of the node's reference position about the center (CX, CY,
// or the centroid of the surface's nodes): a positive delta closes the gap. The elements keep the
// mesh's shape: it is the shape error of a segmented skin as the garment band feels it (the pressure
// it adds where the band must bend over it), whose sensitivities *SENSITIVITY asks for with
// GAP PROFILE lines (solver_cpp/README.md).
struct GapProfile {
  int surface = -1;
  bool has_center = false;
  Eigen::Vector2d center = Eigen::Vector2d::Zero();
  std::map<int, std::pair<double, double>> harmonics;  // k -> (a_k, b_k), mm
  SourceLocation where;
  // cos k theta (sine: sin k theta) at the reference position X about `about`.
  static double basis(int k, bool sine, const Eigen::Vector2d& X, const Eigen::Vector2d& about);
  double offset(const Eigen::Vector2d& X, const Eigen::Vector2d& about) const;
};

// Penalty contact between the nodes of a slave surface and the faces of a master
// surface (*CONTACT PAIR); active in the steps where `active` says so (*MODEL CHANGE).
struct ContactPairDef {
  int slave = -1, master = -1;  // surface indices
  int interaction = -1;
  SourceLocation where;
};

// *LAPLACE PRESSURE on one surface: f = (1 - reference) f_deformed + reference f_reference, the
// membrane load on the deformed contour and the follower pressure fixed by the reference contour's
// curvature (solver_cpp/README.md, Project keywords).
struct LaplaceLoad {
  double tension = 0.0;    // force per unit length
  int profile = -1;        // index into Model::profiles, -1 for constant tension
  double reference = 0.0;  // alpha in [0, 1]: the reference-contour law's share
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

// The parts of a Model that sensitivity parameters set. A parameter's setter changes a
// copy of them, and the solver evaluates the residual of the last step's end state with
// the copy in place of the model's own (solver/sensitivity.hpp).
struct ParameterState {
  std::vector<MaterialDef> materials;
  std::vector<TensionProfile> profiles;
  std::vector<GapProfile> gap_profiles;
  LoadState loads;  // in force at the end of the last step
  // SHAPE parameters: their values (0: the mesh's own shape) and the reference positions they move (node -> shift)
  std::map<std::string, double> shape_coefficients;
  std::map<int, Eigen::Vector2d> node_shifts;
};

// What a parameter changes in the residual, so that dR/dtheta is evaluated over these
// parts only.
struct ParameterScope {
  std::vector<int> elements;               // element indices whose internal force depends on theta
  std::vector<std::pair<int, int>> faces;  // (element, face) whose load depends on theta
  bool prescribed = false;                 // theta moves prescribed displacements
};

// One *SENSITIVITY data line, resolved against the model (deck/sensitivity_parameters.hpp).
struct SensitivityParameter {
  std::string name;  // e.g. MATERIAL:MUSCLE:C10, TENSION:SKIN, PROFILE:GARMENT:A2
  SourceLocation where;
  double scale = 1.0;  // size of the parameter where its value is 0, for the difference step
  bool affine = false;  // R is affine in theta for every element type (one evaluation is exact)
  std::function<double(const ParameterState&)> get;
  std::function<void(ParameterState&, double)> set;
  ParameterScope scope;
  // GAP PROFILE lines: theta moves the contact gaps of this surface's slave nodes by theta times
  // GapProfile::basis(gap_harmonic, gap_sine); dR/dtheta then comes from the contact elements
  // (StaticAnalysis::contact_gap_derivatives), not from the scope.
  int gap_surface = -1;
  int gap_harmonic = 0;
  bool gap_sine = false;
  // SHAPE lines: dX/dtheta of the reference positions theta moves (node, shift per unit theta); the elements in
  // the scope are rebuilt on the moved positions, and the contact elements see them too.
  std::vector<std::pair<int, Eigen::Vector2d>> shape;
};

// *SENSITIVITY: du/dtheta of the last step's converged state for each parameter.
struct SensitivityRequest {
  bool requested = false;
  bool pressure = false;  // also d(-tr sigma / 3)/dtheta per element
  SourceLocation where;
  std::vector<SensitivityParameter> parameters;
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
  std::vector<GapProfile> gap_profiles;
  std::vector<StepDef> steps;
  SensitivityRequest sensitivity;

  int dof_count() const { return 2 * static_cast<int>(coordinates.size()); }
  int surface(const std::string& name) const;   // -1 when unknown
  int material(const std::string& name) const;  // -1 when unknown
  int profile(const std::string& name) const;   // -1 when unknown
  int gap_profile(int surface) const;           // -1 when the surface has none
  std::vector<int> surface_nodes(int surface) const;  // the nodes of its faces, sorted, once each
  // The center of a gap profile's angles: CX, CY, or the centroid of its surface's nodes.
  Eigen::Vector2d gap_center(const GapProfile& profile) const;
  ParameterState parameter_state() const;       // materials, profiles, the last step's loads
};

}  // namespace calfit
