// The parameters that *SENSITIVITY asks about. Each kind turns one data line into a
// SensitivityParameter (model.hpp): its name, how to read and set its value on a
// ParameterState (a copy of the model's materials, tension and gap profiles and last-step loads),
// and the parts of the model it touches (ParameterScope), so that the solver evaluates
// dR/dtheta over those parts only.
//
//   MATERIAL, <material>, <constant>   a law constant (law_constant_names: C10, KV, D1, ...)
//   TENSION, <surface>                 the TENSION of the last step's *LAPLACE PRESSURE there
//   PROFILE, <profile>, A<k> | B<k>    a coefficient of a TYPE=FOURIER tension profile
//                                      (0 when the profile does not list k)
//   GAP PROFILE, <surface>, A<k> | B<k>  a coefficient of the slave surface's *GAP PROFILE (mm;
//                                      0 when it does not list k); through the contact elements
//   VOLUME CHANGE, <elset>             dv of the set's elements in the last step (0 when absent)
//   AXIAL STRETCH                      lambda_z of the last step (1 when absent)
//   RIGID MOTION, <nset>, UX|UY|ANGLE  a component of the set's last-step *RIGID MOTION (0 when
//                                      absent: the set must then be clamped by *BOUNDARY)
//
// A new kind is one resolver function in sensitivity_parameters.cpp and one row in its table.
// A *SENSITIVITY, NAME= block combines its lines, each ending with a weight, into one parameter.
#pragma once

#include "deck/deck_reader.hpp"
#include "model/model.hpp"

namespace calfit {

// Throws DeckError naming the line when the line names nothing the model has.
SensitivityParameter resolve_sensitivity_parameter(const Model& model, const DataLine& line);

// *SENSITIVITY, NAME=<name>: one parameter t that moves every member i by w_i t from the deck's values, so that
// du/dt = sum_i w_i du/dtheta_i in one column (a fitted constant shared by many material groups, a stiffness factor
// of a region: one right-hand side carried along a frictional path instead of one per group). Its value is 0; the
// difference step moves no member by more than its own. GAP PROFILE and SHAPE members are refused.
SensitivityParameter combine_sensitivity_parameters(const Model& model, const std::string& name,
                                                    const SourceLocation& where,
                                                    const std::vector<std::pair<SensitivityParameter, double>>& members);

}  // namespace calfit
