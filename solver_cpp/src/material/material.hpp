// Hyperelastic material interface of calfit-fe.
//
// A material maps the right Cauchy-Green tensor C = F^T F (3x3: plane strain has
// C33 = 1, generalized plane strain may not) to the strain energy W, the second
// Piola-Kirchhoff stress S = 2 dW/dC and the material tangent CC = 4 d2W/dCdC.
// The tangent is stored in Voigt order (11, 22, 33, 12, 23, 13) acting on the
// Green-Lagrange strain with engineering shears, so that dS_voigt = D dE_voigt.
//
// Laws written as W = W_iso(I1bar, I2bar) + U(J) (the isochoric / volumetric split
// of Holzapfel, Nonlinear Solid Mechanics, sec. 6.4) are assembled from the two
// pieces below; the mixed u/p element integrates them separately.
#pragma once

#include <Eigen/Dense>
#include <memory>
#include <string>

namespace calfit {

using Mat3 = Eigen::Matrix3d;
using Mat6 = Eigen::Matrix<double, 6, 6>;

// Tensor indices (i, j) of Voigt position a = 0..5: 11, 22, 33, 12, 23, 13.
constexpr int kVoigtI[6] = {0, 1, 2, 0, 1, 0};
constexpr int kVoigtJ[6] = {0, 1, 2, 1, 2, 2};

class Material {
public:
  virtual ~Material() = default;
  // Strain energy per unit reference volume.
  virtual double energy(const Mat3& C) const = 0;
  // S = 2 dW/dC; when tangent is not null, also D = 4 d2W/dCdC (Voigt, see above).
  virtual void stress(const Mat3& C, Mat3& S, Mat6* tangent) const = 0;
  // True when U(J) is infinite away from J = 1 (D1 = 0): needs a hybrid element.
  virtual bool incompressible() const { return false; }
  virtual std::string description() const = 0;
};

// Isochoric strain energy W_iso(I1bar, I2bar) and its derivatives.
struct IsochoricDerivatives {
  double W = 0, W1 = 0, W2 = 0, W11 = 0, W12 = 0, W22 = 0;
};
class IsochoricEnergy {
public:
  virtual ~IsochoricEnergy() = default;
  virtual IsochoricDerivatives evaluate(double I1bar, double I2bar) const = 0;
  virtual std::string description() const = 0;
};

// Volumetric strain energy U(J) and its first two derivatives.
struct VolumetricDerivatives {
  double U = 0, dU = 0, d2U = 0;
};
class VolumetricEnergy {
public:
  virtual ~VolumetricEnergy() = default;
  virtual VolumetricDerivatives evaluate(double J) const = 0;
  // Incompressible limit: U is a constraint, not an energy (D1 = 0).
  virtual bool is_constraint() const { return false; }
  // The dilatation Theta at which U'(Theta) = p, i.e. G'(p) for the Legendre transform
  // G(p) = sup_Theta [p Theta - U(Theta)] that the mixed u/p element integrates; 1 for
  // the incompressible constraint. Default: Newton's method from Theta = 1.
  virtual double dilatation(double p) const;
  virtual std::string description() const = 0;
};

// W = W_iso(I1bar, I2bar) + U(J), stress and tangent by the chain rule through the
// invariants I1, I2, I3 of C (see hyperelastic.cpp).
class SplitHyperelastic final : public Material {
public:
  SplitHyperelastic(std::shared_ptr<const IsochoricEnergy> iso, std::shared_ptr<const VolumetricEnergy> vol)
      : iso_(std::move(iso)), vol_(std::move(vol)) {}
  double energy(const Mat3& C) const override;
  void stress(const Mat3& C, Mat3& S, Mat6* tangent) const override;
  bool incompressible() const override { return vol_->is_constraint(); }
  std::string description() const override { return iso_->description() + " + " + vol_->description(); }
  const IsochoricEnergy& isochoric() const { return *iso_; }
  const VolumetricEnergy& volumetric() const { return *vol_; }
  // Stress and tangent of W_iso alone (the mixed element adds p J C^-1 itself).
  void isochoric_stress(const Mat3& C, Mat3& S, Mat6* tangent) const;

private:
  std::shared_ptr<const IsochoricEnergy> iso_;
  std::shared_ptr<const VolumetricEnergy> vol_;
};

// St Venant-Kirchhoff: W = lambda/2 (tr E)^2 + mu E:E, the finite-strain reading of
// *ELASTIC that CalculiX uses with NLGEOM.
class StVenantKirchhoff final : public Material {
public:
  StVenantKirchhoff(double young, double poisson);
  double energy(const Mat3& C) const override;
  void stress(const Mat3& C, Mat3& S, Mat6* tangent) const override;
  std::string description() const override;

private:
  double young_, poisson_, lambda_, mu_;
};

}  // namespace calfit
