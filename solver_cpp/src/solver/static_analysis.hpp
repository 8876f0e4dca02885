// StaticAnalysis: the quasi-static incremental solution of a Model. It numbers the unknowns (the nodal
// displacements, then the pressures of the hybrid elements), solves each step in load increments by Newton's method
// (newton.hpp), and gives the converged state's fields (field_output.hpp) and what the parameter sensitivities need
// (sensitivity.hpp). Its parts: static_analysis.cpp, the unknowns; newton.cpp, the increments of a step and the
// Newton iterations of each; line_search.cpp; analysis_loads.cpp, the loads and kinematics of a step;
// analysis_contact.cpp, penalty contact and friction; analysis_assembly.cpp, residual, tangent and field output;
// analysis_parameters.cpp, what the sensitivities need (analysis_support.hpp: the helpers they share).
#pragma once

#include "element/solid_element.hpp"
#include "load/edge_loads.hpp"
#include "model/model.hpp"
#include "solver/field_output.hpp"
#include "solver/newton.hpp"
#include "solver/sparse_system.hpp"

#include <array>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

namespace calfit {

class StaticAnalysis {
public:
  StaticAnalysis(const Model& model, SolverSettings settings);
  StepResult run_step(int step, const std::function<void(const std::string&)>& log);
  FieldOutput output();  // re-evaluates the residual for the reactions
  int free_dof_count() const { return free_dofs_; }
  const std::string& linear_solver() const { return linear_solver_; }
  const Timings& timings() const { return timings_; }

  // ---- for parameter sensitivities (solver/sensitivity.hpp) --------------------------
  // Unknowns of the last converged state: 2 n_nodes displacements, then hybrid pressures.
  const Eigen::VectorXd& solution() const { return u_; }
  // R(u) = f_int - f_ext at the end of the current step (every load at its full value).
  Eigen::VectorXd residual(const Eigen::VectorXd& u);
  // The part of R(u) at the end of the current step that `scope` covers, with the
  // materials, tension profiles and loads of `state` in place of the model's own; with
  // scope.prescribed, the prescribed entries of u take state's values first.
  Eigen::VectorXd scoped_residual(const ParameterState& state, const ParameterScope& scope, const Eigen::VectorXd& u) const;
  // scoped_residual(model's own state, scope, solution()), from the element forces that
  // the last evaluation at the converged state left (recomputed if another came since).
  Eigen::VectorXd converged_scoped_residual(const ParameterScope& scope);
  // Element pressures -tr(sigma)/3 (volume averages, as written to the VTU) at u; the
  // elements of `scope` with the materials of `state`.
  Eigen::VectorXd element_pressures(const ParameterState& state, const ParameterScope& scope,
                                    const Eigen::VectorXd& u) const;
  // Prescribed displacements (dof -> value) that `loads` hold at the end of their step:
  // the *BOUNDARY values and the end positions of the *RIGID MOTION node sets. The
  // sensitivities take u_p(theta) from here (a parameter that moves prescribed dofs is
  // differentiated through it); prepare_step ramps the *BOUNDARY ones linearly and the
  // rigid motions in angle (prepare_rigid_motions), which end at the same values.
  std::map<int, double> prescribed_values(const LoadState& loads) const;
  // Solves K X = B with K = dR/du at the converged solution of the current step, for
  // every column of B (full length: prescribed rows of B are ignored, of X set to 0).
  // Returns false when K is singular.
  bool solve_tangent(const Eigen::MatrixXd& B, Eigen::MatrixXd& X);
  // dR/dtheta of the contact elements at the converged state for *SENSITIVITY's GAP PROFILE and SHAPE parameters
  // (the slaves' offsets, the positions moved; other columns zero): what the scoped residuals do not see
  // (n_dofs x parameters).
  Eigen::MatrixXd contact_parameter_derivatives();
  // With Coulomb friction the converged state depends on the loading path: the sensitivities of *SENSITIVITY's
  // parameters are then carried along it, one solve per converged increment (sensitivity.hpp, (4));
  // path_sensitivities() holds du/dtheta of the last one (n_dofs x parameters).
  bool carries_path_sensitivities() const { return carries_path_sensitivities_; }
  const Eigen::MatrixXd& path_sensitivities() const { return path_du_; }

private:
  struct FaceLoad {
    int element;
    std::vector<int> local;  // element-local node indices along the face
    double start = 0, end = 0;         // pressure (follower)
    Eigen::VectorXd t_start, t_end;    // nodal tension of the deformed-contour share (Laplace)
    Eigen::VectorXd p_start, p_end;    // nodal pressure of the reference-contour share (Laplace)
    Eigen::VectorXd tension(double lambda) const { return t_start + lambda * (t_end - t_start); }
    Eigen::VectorXd reference_pressure(double lambda) const { return p_start + lambda * (p_end - p_start); }
  };
  // The garment's load on one face of a *LAPLACE PRESSURE surface, f = (1 - alpha) f_deformed(T) +
  // alpha f_reference(T) (edge_loads.hpp, garment_load): the membrane tension of the first share and the
  // nodal follower pressure of the second, summed over the surfaces that share the face. Both are linear in
  // T, so the step ramps them linearly, as it ramps T.
  struct LaplaceFace {
    Eigen::VectorXd tension;             // (1 - alpha) T at the face's nodes
    Eigen::VectorXd reference_pressure;  // alpha p0 at the face's nodes (zero where alpha = 0)
  };
  struct Ramp {
    int dof;
    double start, end;
  };
  // A *RIGID MOTION over the step: translation and angle ramped from start to end about
  // the end's centre. `mismatch` (per node) is how far a node stood from the motion's
  // start at the start of the step (nonzero when the motion is new and the node had
  // moved freely); it fades out linearly, as a *BOUNDARY ramps from the current value.
  struct RigidRamp {
    std::vector<int> nodes;
    Eigen::Vector2d center, translation_start, translation_end;
    double angle_start = 0, angle_end = 0;  // degrees
    std::vector<Eigen::Vector2d> mismatch;
  };
  struct Evaluation {
    bool ok = false;
    double norm = 0, reference = 0;
  };

  // One contact pair: its slave nodes, master segments and the friction history.
  struct ContactState {
    int pair = -1;
    ContactLaw law;
    std::vector<int> slave_nodes;
    std::vector<double> slave_weight;          // tributary length x thickness
    std::vector<std::array<int, 2>> segments;  // master sub-segments, counter-clockwise
    std::vector<int> previous, next;           // neighbouring segment of each (-1 at an open end)
    std::vector<double> master_weight;         // per node: tributary length (for output)
    std::vector<ContactHistory> history, trial;
    std::vector<ContactPoint> points;
    // Within the Newton iterations of one increment (see hold_chattering_contacts): each slave node's last slip
    // direction at an iterate (0: none yet), and whether it is held sticking (kHeld) or was released from it.
    std::vector<int> iterate_slip;
    std::vector<char> hold;
    // Each slave node's local contact element at the last evaluation (its nodes, empty if none, and the master
    // segment), and, when sensitivities are carried through friction, d(xi, shear, gap of its history)/dtheta
    // (3 x parameters, empty while zero).
    std::vector<std::vector<int>> element_nodes;
    std::vector<int> element_segment;
    std::vector<Eigen::MatrixXd> history_sensitivity;
    // *GAP PROFILE: each slave node's offset (mm, 0 without a profile), and d(offset)/dtheta for *SENSITIVITY's
    // GAP PROFILE parameters (slave nodes x parameters; empty without such a parameter on this pair's slave).
    std::vector<double> slave_offset;
    Eigen::MatrixXd gap_factors;
    // SHAPE parameters: d(slave weight)/dtheta (slave nodes x parameters; empty without SHAPE parameters)
    Eigen::MatrixXd weight_derivatives;
  };
  static constexpr char kFree = 0, kHeld = 1, kReleased = 2;
  struct ContactElement {
    std::vector<int> dofs;
    Eigen::MatrixXd K;
    // The couplings the matrix pattern is given for it: its own and those of the master segments within
    // kContactReach of its segment, where the node may slide next (rebuilding the pattern costs an ordering)
    std::vector<int> reach;
  };
  static constexpr int kContactReach = 3;

  void prepare_step(int step);
  void build_contacts();
  // Adds the contact forces at u to residual_; collects contact elements for the tangent.
  void contact_residual(const Eigen::VectorXd& u, bool tangent, std::vector<ContactElement>& elements);
  // With friction: the contact history of the reference state (where each slave node touches or faces the
  // master), so that a node touching within the first increment is anchored like any later one.
  void anchor_contacts();
  // Coulomb friction within Newton's iterations (see contact_residual). At an iterate (the last state
  // evaluated): holds sticking the slave nodes that slip opposite to the way they slipped at an earlier iterate
  // of the increment, true if it held any (the residual must then be evaluated again). At a converged iterate:
  // releases the held nodes that the law would let slip, true if any (the increment then iterates on).
  // forget_contact_iterates() clears both at the start and end of an increment's iterations.
  bool hold_chattering_contacts();
  bool release_slipping_contacts();
  void forget_contact_iterates();
  // A new system whose pattern holds system_contact_dofs_ (the couplings of the one before: prepare_step clears
  // them) and `contact`'s, added to them.
  void rebuild_system(const std::vector<ContactElement>& contact);
  // After a converged increment, before its contact history is committed: du/dtheta of the increment and the
  // history's sensitivity it leaves (sensitivity.hpp, (4)-(5)).
  void propagate_path_sensitivities();
  // The contact's part of dR/dtheta (GAP PROFILE, SHAPE) of the touching slave nodes' elements at the last
  // evaluation: of every pair, or (frictionless_only) of those without friction, whose part the path carries.
  Eigen::MatrixXd contact_derivatives(bool frictionless_only) const;
  // Slave node i's contact element (derivatives D, its nodes): its local residual's and left history's derivatives
  // with respect to the GAP PROFILE and SHAPE parameters (2 n_nodes x parameters, 3 x parameters).
  void contact_parameter_parts(const ContactState& c, std::size_t i, const ContactHistoryDerivatives& D,
                               Eigen::MatrixXd& dr, Eigen::MatrixXd& dh) const;
  bool has_contact_parameters() const;
  // Internal forces of `elements` with state's materials at u and the committed increment's load fraction; in the
  // last step under state's volume change and axial stretch, ramped from the step's start.
  Eigen::VectorXd increment_residual(const ParameterState& state, const std::vector<int>& elements,
                                     const Eigen::VectorXd& u) const;
  // Internal forces of `elements` rebuilt with state's materials on its moved reference positions under
  // kinematics_of(e), at u, summed into a full-length vector (the sensitivities' dR/dtheta); throws `inverted`
  // where an element turns inside out.
  Eigen::VectorXd rebuilt_element_forces(const ParameterState& state, const std::vector<int>& elements,
                                         const std::function<ElementKinematics(int)>& kinematics_of,
                                         const Eigen::VectorXd& u, const char* inverted) const;
  // Residual R = f_int - f_ext at load fraction lambda; the tangent too if asked.
  Evaluation evaluate(const Eigen::VectorXd& u, double lambda, bool tangent);
  // Moves u along the Newton correction du by the step the line search chooses and returns the evaluation
  // (with tangent) there; `start` is the evaluation at u, whose residual residual_ holds. Not ok when every
  // step inverts an element.
  Evaluation line_search(Eigen::VectorXd& u, const Eigen::VectorXd& du, double lambda, const Evaluation& start);
  double slope_along(const Eigen::VectorXd& direction) const;  // direction . R over the free dofs
  void apply_prescribed(Eigen::VectorXd& u, double lambda) const;
  void prepare_rigid_motions(const LoadState& before, const LoadState& now);
  // Growth and axial stretch of element e at load fraction lambda of the current step.
  ElementKinematics kinematics(int element, double lambda) const;
  // The garment's load of every face of the Laplace-loaded surfaces: (element, face) -> its two shares.
  std::map<std::pair<int, int>, LaplaceFace> laplace_faces(const LoadState& state,
                                                           const std::vector<TensionProfile>& profiles) const;
  // The reference contour's nodal pressures p0 of one surface whose faces carry the nodal tensions `tensions`
  // (same order as `faces`): -(F0 . n0) / L0 at the face corners, F0 the membrane load on the reference
  // contour, linear along each face; returned per face at its nodes (analysis_loads.cpp says why).
  std::vector<Eigen::VectorXd> reference_pressures(const std::vector<Face>& faces,
                                                   const std::vector<Eigen::VectorXd>& tensions) const;
  FaceLoad unloaded_face(const std::pair<int, int>& key) const;  // element and face nodes, no load yet
  // Element e as the end of the current step sees it with the parameters of `state`, for
  // the sensitivities: built with state's material, under state's end-of-step growth and
  // axial stretch (what evaluate() imposes at lambda = 1).
  struct ParameterElement {
    std::unique_ptr<Element> element;
    ElementKinematics kinematics;
    bool internal_force(const ElementVector& ue, ElementVector& f) const {
      return element->internal_force(ue, kinematics, f, nullptr);
    }
    ElementState state(const ElementVector& ue) const { return element->state(ue, kinematics); }
  };
  ParameterElement element_for(const ParameterState& state, int e) const;
  ElementKinematics end_of_step_kinematics(const ParameterState& state, int e) const;  // element_for's kinematics
  // R -= the end-of-step loads of `faces` (follower pressures, Laplace) with state's loads and profiles, at u.
  void subtract_face_loads(const ParameterState& state, const std::vector<std::pair<int, int>>& faces,
                           const Eigen::VectorXd& u, Eigen::VectorXd& R) const;
  EdgeNodes face_positions(const FaceLoad& f, const Eigen::VectorXd& u) const;

  const Model& model_;
  SolverSettings settings_;
  ElementVector local_unknowns(const Eigen::VectorXd& u, int element) const;

  std::vector<std::unique_ptr<Element>> elements_;
  std::vector<ContactState> contacts_;
  int current_step_ = 0;
  std::vector<char> free_;
  std::vector<std::vector<int>> system_contact_dofs_;  // contact couplings in system_'s pattern
  int n_dofs_ = 0;            // displacements, then hybrid pressures
  bool saddle_point_ = false;  // hybrid elements make the tangent indefinite
  double model_size_ = 0.0;    // diagonal of the reference bounding box
  std::vector<std::vector<int>> element_dofs_;
  Eigen::VectorXd u_;  // committed displacement
  Eigen::VectorXd tangent_u_;   // where the matrix in system_ was last assembled ...
  double tangent_lambda_ = -1;  // ... and at which load fraction
  Eigen::VectorXd forces_u_;    // where element_force_ was last computed ...
  double forces_lambda_ = -1;   // ... and at which load fraction
  double last_lambda_ = 0.0;  // load fraction of u_ within its step
  Eigen::VectorXd residual_, f_ext_;
  std::unique_ptr<SparseSystem> system_;
  std::vector<Ramp> prescribed_, forces_;
  std::vector<RigidRamp> rigid_motions_;
  // *VOLUME CHANGE dv per element and *AXIAL STRETCH lambda_z at the two ends of the step.
  std::vector<double> volume_change_start_, volume_change_end_;
  double axial_stretch_start_ = 1.0, axial_stretch_end_ = 1.0;
  std::vector<FaceLoad> pressure_faces_, laplace_faces_;
  int free_dofs_ = 0;
  std::string linear_solver_ = "none";
  Timings timings_;
  // per-element buffers filled in parallel, scattered serially
  std::vector<ElementVector> element_force_;
  std::vector<ElementMatrix> element_tangent_;
  bool carries_path_sensitivities_ = false;
  // SHAPE parameters: node -> (parameter index, dX/dtheta) of each that moves it
  std::map<int, std::vector<std::pair<int, Eigen::Vector2d>>> shape_of_node_;
  Eigen::MatrixXd path_du_;
};

}  // namespace calfit
