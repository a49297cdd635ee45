//! Hyperelastic materials in terms of the deformation gradient F.
//!
//! Each gives the energy density psi(F), the second Piola-Kirchhoff stress S, the first
//! Piola-Kirchhoff stress P = F S and its derivative dP/dF (the tangent), stored as a 9x9
//! matrix A[(3i+J), (3k+L)] = dP_iJ / dF_kL.

use nalgebra::{Matrix3, SMatrix};

pub type Tangent = SMatrix<f64, 9, 9>;

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MaterialKind {
    /// Saint Venant-Kirchhoff: S = lambda tr(E) I + 2 mu E (the paper's).
    StVenantKirchhoff,
    /// Small-strain linear elasticity (P = sigma(sym(F - I))).
    Linear,
    /// Compressible Neo-Hookean: psi = mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2.
    NeoHookean,
}

impl MaterialKind {
    pub fn name(self) -> &'static str {
        match self {
            MaterialKind::StVenantKirchhoff => "svk",
            MaterialKind::Linear => "linear",
            MaterialKind::NeoHookean => "neo-hookean",
        }
    }
    pub fn parse(s: &str) -> Option<Self> {
        match s.to_ascii_lowercase().as_str() {
            "svk" | "stvk" | "saint-venant-kirchhoff" | "st-venant-kirchhoff" => Some(Self::StVenantKirchhoff),
            "linear" => Some(Self::Linear),
            "neo-hookean" | "neohookean" | "nh" => Some(Self::NeoHookean),
            _ => None,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MaterialParams {
    pub kind: MaterialKind,
    pub young_pa: f64,
    pub poisson: f64,
}

impl Default for MaterialParams {
    fn default() -> Self {
        // Liver parenchyma: a few kPa; Poisson 0.49 as in the paper.
        Self { kind: MaterialKind::StVenantKirchhoff, young_pa: 4500.0, poisson: 0.49 }
    }
}

impl MaterialParams {
    /// Lame parameters in N/mm^2 (MPa).
    pub fn lame_n_per_mm2(&self) -> (f64, f64) {
        let e = self.young_pa * 1e-6;
        let nu = self.poisson;
        (e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)), e / (2.0 * (1.0 + nu)))
    }
    pub fn validate(&self) -> Result<(), crate::Invalid> {
        if !(self.young_pa.is_finite() && YOUNG_RANGE_PA.contains(&self.young_pa)) {
            return Err(crate::Invalid(format!(
                "Young's modulus {} Pa must lie in [{}, {:e}] Pa: liver tissue is 1-100 kPa; the load calibration scales forces with it, and at 1e308 Pa they overflow and the solve never ends",
                crate::shown(self.young_pa),
                YOUNG_RANGE_PA.start(),
                YOUNG_RANGE_PA.end()
            )));
        }
        if !(POISSON_RANGE.contains(&self.poisson)) {
            return Err(crate::Invalid(format!(
                "Poisson's ratio {} must lie in [{}, {}]: soft tissue is 0.45-0.49; the trilinear hexahedra lock as it nears 0.5 (at 0.4999999 the phantom moved 0.39 mm instead of 10, in 7 minutes) and a Neo-Hookean solve near -1 does not finish",
                self.poisson,
                POISSON_RANGE.start(),
                POISSON_RANGE.end()
            )));
        }
        Ok(())
    }
    pub fn material(&self) -> Material {
        let (lambda, mu) = self.lame_n_per_mm2();
        Material { kind: self.kind, lambda, mu }
    }
}

/// The Young's moduli a solve can afford (see `MaterialParams::validate`).
pub const YOUNG_RANGE_PA: std::ops::RangeInclusive<f64> = 1.0..=1e9;

/// The Poisson's ratios a solve can afford (see `MaterialParams::validate`).
pub const POISSON_RANGE: std::ops::RangeInclusive<f64> = 0.0..=0.495;

/// The material drawn per sample of a dataset: Poisson's ratio uniform in
/// [`poisson_min`, `poisson_max`], Neo-Hookean with probability `neo_hookean_fraction` (else the
/// dataset's own kind); Young's modulus stays the dataset's (the network predicts displacement
/// from observed displacement, in which a common stiffness factor cancels).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MaterialVariation {
    pub poisson_min: f64,
    pub poisson_max: f64,
    pub neo_hookean_fraction: f64,
}

impl Default for MaterialVariation {
    /// The range: nearly incompressible parenchyma, half of the samples Neo-Hookean.
    fn default() -> Self {
        Self { poisson_min: 0.45, poisson_max: 0.49, neo_hookean_fraction: 0.5 }
    }
}

impl MaterialVariation {
    pub fn validate(&self) -> Result<(), crate::Invalid> {
        let ok = |v: f64| POISSON_RANGE.contains(&v);
        if !(ok(self.poisson_min) && ok(self.poisson_max) && self.poisson_min <= self.poisson_max) {
            return Err(crate::Invalid(format!(
                "the Poisson's ratio range {}-{} must be ordered and lie in [{}, {}]",
                self.poisson_min,
                self.poisson_max,
                POISSON_RANGE.start(),
                POISSON_RANGE.end()
            )));
        }
        if !(self.neo_hookean_fraction.is_finite() && (0.0..=1.0).contains(&self.neo_hookean_fraction)) {
            return Err(crate::Invalid(format!(
                "the Neo-Hookean fraction {} must lie in [0, 1]",
                self.neo_hookean_fraction
            )));
        }
        Ok(())
    }

    /// One draw around `base` from two uniform numbers in [0, 1).
    pub fn draw(&self, base: MaterialParams, u_poisson: f64, u_kind: f64) -> MaterialParams {
        let kind = if u_kind < self.neo_hookean_fraction { MaterialKind::NeoHookean } else { base.kind };
        MaterialParams { kind, poisson: self.poisson_min + u_poisson * (self.poisson_max - self.poisson_min), ..base }
    }
}

/// A hyperelastic material: energy density psi(F), second Piola-Kirchhoff stress S, first
/// Piola-Kirchhoff stress P = F S and the tangent dP/dF. Lame parameters are in N/mm^2.
pub trait HyperelasticMaterial: Send + Sync {
    fn energy_density(&self, f: &Matrix3<f64>) -> f64;
    fn pk2(&self, f: &Matrix3<f64>) -> Matrix3<f64>;
    fn pk1(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        f * self.pk2(f)
    }
    /// P and dP/dF together (they share intermediate results).
    fn pk1_and_tangent(&self, f: &Matrix3<f64>) -> (Matrix3<f64>, Tangent);
}

#[inline]
fn idx(i: usize, j: usize) -> usize {
    3 * i + j
}

/// Saint Venant-Kirchhoff: S = lambda tr(E) I + 2 mu E.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StVenantKirchhoff {
    pub lambda: f64,
    pub mu: f64,
}

impl HyperelasticMaterial for StVenantKirchhoff {
    fn energy_density(&self, f: &Matrix3<f64>) -> f64 {
        let e = green_strain(f);
        0.5 * self.lambda * e.trace().powi(2) + self.mu * e.component_mul(&e).sum()
    }
    fn pk2(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        let e = green_strain(f);
        Matrix3::identity() * (self.lambda * e.trace()) + e * (2.0 * self.mu)
    }
    fn pk1_and_tangent(&self, f: &Matrix3<f64>) -> (Matrix3<f64>, Tangent) {
        // A_iJkL = d_ik S_LJ + lambda F_iJ F_kL + mu (F_iL F_kJ + (F F^T)_ik d_JL)
        let (l, m) = (self.lambda, self.mu);
        let s = self.pk2(f);
        let ff = f * f.transpose();
        let mut a = Tangent::zeros();
        for i in 0..3 {
            for jj in 0..3 {
                for k in 0..3 {
                    for ll in 0..3 {
                        let mut v = l * f[(i, jj)] * f[(k, ll)] + m * f[(i, ll)] * f[(k, jj)];
                        if i == k {
                            v += s[(ll, jj)];
                        }
                        if jj == ll {
                            v += m * ff[(i, k)];
                        }
                        a[(idx(i, jj), idx(k, ll))] = v;
                    }
                }
            }
        }
        (f * s, a)
    }
}

/// Small-strain linear elasticity: P = sigma(eps), eps = sym(F - I).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinearElastic {
    pub lambda: f64,
    pub mu: f64,
}

impl HyperelasticMaterial for LinearElastic {
    fn energy_density(&self, f: &Matrix3<f64>) -> f64 {
        let eps = small_strain(f);
        0.5 * self.lambda * eps.trace().powi(2) + self.mu * eps.component_mul(&eps).sum()
    }
    fn pk2(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        // No finite-strain S exists; F^-1 P keeps P = F S consistent.
        let p = self.pk1(f);
        f.try_inverse().map(|fi| fi * p).unwrap_or(p)
    }
    fn pk1(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        let eps = small_strain(f);
        Matrix3::identity() * (self.lambda * eps.trace()) + eps * (2.0 * self.mu)
    }
    fn pk1_and_tangent(&self, f: &Matrix3<f64>) -> (Matrix3<f64>, Tangent) {
        let mut a = Tangent::zeros();
        for i in 0..3 {
            for jj in 0..3 {
                for k in 0..3 {
                    for ll in 0..3 {
                        let mut v = 0.0;
                        if i == jj && k == ll {
                            v += self.lambda;
                        }
                        if i == k && jj == ll {
                            v += self.mu;
                        }
                        if i == ll && jj == k {
                            v += self.mu;
                        }
                        a[(idx(i, jj), idx(k, ll))] = v;
                    }
                }
            }
        }
        (self.pk1(f), a)
    }
}

/// Compressible Neo-Hookean: psi = mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NeoHookean {
    pub lambda: f64,
    pub mu: f64,
}

impl HyperelasticMaterial for NeoHookean {
    fn energy_density(&self, f: &Matrix3<f64>) -> f64 {
        let j = f.determinant();
        if j <= 0.0 {
            return f64::INFINITY;
        }
        let lj = j.ln();
        0.5 * self.mu * ((f.transpose() * f).trace() - 3.0) - self.mu * lj + 0.5 * self.lambda * lj * lj
    }
    fn pk2(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        let c_inv = (f.transpose() * f).try_inverse().unwrap_or_else(Matrix3::identity);
        let lj = f.determinant().max(1e-300).ln();
        (Matrix3::identity() - c_inv) * self.mu + c_inv * (self.lambda * lj)
    }
    fn pk1(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        let fit = f.try_inverse().unwrap_or_else(Matrix3::identity).transpose();
        let lj = f.determinant().max(1e-300).ln();
        (f - fit) * self.mu + fit * (self.lambda * lj)
    }
    fn pk1_and_tangent(&self, f: &Matrix3<f64>) -> (Matrix3<f64>, Tangent) {
        // A_iJkL = mu d_ik d_JL + (mu - lambda ln J) Fi_Li Fi_Jk + lambda Fi_Ji Fi_Lk
        let (l, m) = (self.lambda, self.mu);
        let fi = f.try_inverse().unwrap_or_else(Matrix3::identity);
        let lj = f.determinant().max(1e-300).ln();
        let mut a = Tangent::zeros();
        for i in 0..3 {
            for jj in 0..3 {
                for k in 0..3 {
                    for ll in 0..3 {
                        let mut v = (m - l * lj) * fi[(ll, i)] * fi[(jj, k)] + l * fi[(jj, i)] * fi[(ll, k)];
                        if i == k && jj == ll {
                            v += m;
                        }
                        a[(idx(i, jj), idx(k, ll))] = v;
                    }
                }
            }
        }
        (self.pk1(f), a)
    }
}

/// A material chosen at run time (a copyable value that dispatches to the trait's impls).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Material {
    pub kind: MaterialKind,
    pub lambda: f64,
    pub mu: f64,
}

impl Material {
    fn with<R>(&self, f: impl FnOnce(&dyn HyperelasticMaterial) -> R) -> R {
        let (lambda, mu) = (self.lambda, self.mu);
        match self.kind {
            MaterialKind::StVenantKirchhoff => f(&StVenantKirchhoff { lambda, mu }),
            MaterialKind::Linear => f(&LinearElastic { lambda, mu }),
            MaterialKind::NeoHookean => f(&NeoHookean { lambda, mu }),
        }
    }
}

impl HyperelasticMaterial for Material {
    fn energy_density(&self, f: &Matrix3<f64>) -> f64 {
        self.with(|m| m.energy_density(f))
    }
    fn pk2(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        self.with(|m| m.pk2(f))
    }
    fn pk1(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        self.with(|m| m.pk1(f))
    }
    fn pk1_and_tangent(&self, f: &Matrix3<f64>) -> (Matrix3<f64>, Tangent) {
        self.with(|m| m.pk1_and_tangent(f))
    }
}

pub fn green_strain(f: &Matrix3<f64>) -> Matrix3<f64> {
    (f.transpose() * f - Matrix3::identity()) * 0.5
}

pub fn small_strain(f: &Matrix3<f64>) -> Matrix3<f64> {
    let g = f - Matrix3::identity();
    (g + g.transpose()) * 0.5
}
