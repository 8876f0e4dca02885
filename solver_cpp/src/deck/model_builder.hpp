// ModelBuilder, internal to the deck parser: deck keywords -> Model, one handler per keyword, each in the file of
// its keyword family (model_builder.cpp: the keyword table, the checks and lookups the handlers share, the
// whole-model checks; keywords_mesh.cpp: *NODE, *ELEMENT, *NSET, *ELSET, *SURFACE; keywords_materials.cpp:
// *MATERIAL, *HYPERELASTIC, *ELASTIC, *SOLID SECTION; keywords_steps.cpp: *STEP, *STATIC, *BOUNDARY, *CLOAD, *DLOAD,
// output requests, *END STEP; keywords_garment.cpp: *TENSION PROFILE, *LAPLACE PRESSURE; keywords_kinematics.cpp:
// *VOLUME CHANGE, *AXIAL STRETCH, *RIGID MOTION; keywords_contact.cpp: *SURFACE INTERACTION, *SURFACE BEHAVIOR,
// *FRICTION, *CONTACT PAIR, *MODEL CHANGE, *GAP PROFILE; keywords_sensitivity.cpp: *SENSITIVITY, whose data lines
// sensitivity_parameters.cpp resolves). The rest of the engine calls build_model (deck/build_model.hpp).
#pragma once

#include "deck/deck_reader.hpp"
#include "model/model.hpp"

#include <cstddef>
#include <functional>
#include <map>
#include <string>
#include <vector>

namespace calfit::deck_building {

// The fields of one data line, read by position: a missing or empty field is an error naming `what`.
struct Context {
  const DataLine& line;
  std::size_t field_count() const { return line.fields.size(); }
  const std::string& field(std::size_t i, const std::string& what) const {
    if (i >= line.fields.size() || line.fields[i].empty()) throw DeckError(line.where, what + " is missing");
    return line.fields[i];
  }
  double number(std::size_t i, const std::string& what) const { return to_double(field(i, what), line.where, what); }
  int integer(std::size_t i, const std::string& what) const { return to_int(field(i, what), line.where, what); }
};

class ModelBuilder {
public:
  explicit ModelBuilder(const std::string& path) { model_.deck_path = path; }

  Model build();

private:
  using Handler = std::function<void(const KeywordBlock&)>;
  Model model_;
  int current_material_ = -1;
  bool material_has_law_ = false;
  bool in_step_ = false;
  bool step_has_static_ = false;
  LoadState loads_;                 // state carried from step to step
  // *SENSITIVITY lines, resolved once the whole model is known: one parameter each, or, in a NAME= block, the
  // block's lines with their weights as one parameter (`combine_sensitivity_parameters`)
  struct PendingSensitivity {
    std::string combined_name;  // empty: the one line is the parameter
    SourceLocation where;
    std::vector<std::pair<DataLine, double>> lines;
  };
  std::vector<PendingSensitivity> sensitivity_entries_;
  int current_interaction_ = -1;  // the *SURFACE INTERACTION that *SURFACE BEHAVIOR and *FRICTION refine
  std::map<int, double> model_bcs_;  // *BOUNDARY given before the first step

  // ---- model_builder.cpp: the keyword table, context checks, lookups, whole-model checks -----------------------
  std::map<std::string, Handler> handlers();
  static std::string unknown_keyword_message(const std::string& name);
  void model_data(const KeywordBlock& b) const;
  void step_data(const KeywordBlock& b) const;
  static void no_data(const KeywordBlock& b);
  static void needs_data(const KeywordBlock& b);
  static void field_count(const DataLine& line, std::size_t min, std::size_t max, const std::string& what);
  static void require(bool ok, const DataLine& line, const std::string& message);
  // Data lines `k, a_k, b_k` of a Fourier series (*TENSION PROFILE, TYPE=FOURIER; *GAP PROFILE), k >= lowest
  // (`why` says why not lower), each k once.
  static void read_harmonics(const KeywordBlock& b, const std::string& what, int lowest, const std::string& why,
                             std::map<int, std::pair<double, double>>& harmonics);
  int node(const std::string& text, const SourceLocation& where) const;
  std::vector<int> nodes_of(const std::string& text, const SourceLocation& where) const;
  std::vector<int> elements_of(const std::string& text, const SourceLocation& where) const;
  static int dof_number(const std::string& text, const SourceLocation& where);
  static int face_label(const std::string& text, const std::string& prefix, const SourceLocation& where);
  // A step's OP= on `target`: NEW clears what earlier keywords and steps put there, MOD (the default) keeps it.
  template <typename Map>
  static void apply_op(const KeywordBlock& b, Map& target) {
    const std::string op = upper(b.value("OP").value_or("MOD"));
    if (op == "NEW") {
      target.clear();
    } else if (op != "MOD") {
      throw DeckError(b.where, "OP must be MOD or NEW");
    }
  }
  void heading(const KeywordBlock& b);
  void finish(const SourceLocation& last);

  // ---- keywords_mesh.cpp: *NODE, *ELEMENT, *NSET, *ELSET, *SURFACE ------------------------------------------------
  void node(const KeywordBlock& b);
  void element(const KeywordBlock& b);
  template <typename Resolve>
  void fill_set(const KeywordBlock& b, std::vector<int>& target, Resolve resolve, const std::string& item);
  void node_set(const KeywordBlock& b);
  void element_set(const KeywordBlock& b);
  void surface(const KeywordBlock& b);
  void check_geometry(const ElementDef& e) const;

  // ---- keywords_materials.cpp: *MATERIAL, *HYPERELASTIC, *ELASTIC, *SOLID SECTION ---------------------------------
  void material(const KeywordBlock& b);
  void check_material_complete() const;
  static constexpr std::size_t kConstantsPerLine = 8;  // CalculiX's material data lines
  std::vector<DataLine> law_data_lines(const KeywordBlock& b, std::size_t count);
  void set_law(LawConstants constants);
  LawConstants read_constants(const KeywordBlock& b, const std::string& law, int order, const std::string& what,
                              std::size_t optional = 0);
  void hyperelastic(const KeywordBlock& b);
  void elastic(const KeywordBlock& b);
  void solid_section(const KeywordBlock& b);

  // ---- keywords_steps.cpp: *STEP, *STATIC, *BOUNDARY, *CLOAD, *DLOAD, output requests, *END STEP ------------------
  void step(const KeywordBlock& b);
  void static_procedure(const KeywordBlock& b);
  void boundary(const KeywordBlock& b);
  void cload(const KeywordBlock& b);
  void dload(const KeywordBlock& b);
  void output_request(const KeywordBlock& b);
  void end_step(const KeywordBlock& b);

  // ---- keywords_garment.cpp: *TENSION PROFILE, *LAPLACE PRESSURE --------------------------------------------------
  void tension_profile(const KeywordBlock& b);
  static void read_table_profile(const KeywordBlock& b, TensionProfile& p);
  static void read_fourier_profile(const KeywordBlock& b, TensionProfile& p);
  void laplace_pressure(const KeywordBlock& b);

  // ---- keywords_kinematics.cpp: *VOLUME CHANGE, *AXIAL STRETCH, *RIGID MOTION -------------------------------------
  static const DataLine& one_data_line(const KeywordBlock& b, std::size_t count, const std::string& what);
  void volume_change(const KeywordBlock& b);
  void axial_stretch(const KeywordBlock& b);
  void rigid_motion(const KeywordBlock& b);
  void check_not_rigid(int node, const SourceLocation& where) const;

  // ---- keywords_contact.cpp: *SURFACE INTERACTION, *SURFACE BEHAVIOR, *FRICTION, *CONTACT PAIR, *MODEL CHANGE,
  // *GAP PROFILE ------------------------------------------------------------------------------------------------
  void surface_interaction(const KeywordBlock& b);
  InteractionDef& interaction_for(const KeywordBlock& b);
  void surface_behavior(const KeywordBlock& b);
  void friction(const KeywordBlock& b);
  int surface_named(const std::string& name, const SourceLocation& where) const;
  void contact_pair(const KeywordBlock& b);
  void model_change(const KeywordBlock& b);
  void gap_profile(const KeywordBlock& b);

  // ---- keywords_sensitivity.cpp: *SENSITIVITY ---------------------------------------------------------------------
  void sensitivity(const KeywordBlock& b);
  void resolve_sensitivities();
};

}  // namespace calfit::deck_building
