//! Static cloth parameters from drapes (paper 001): an XPBD cloth with
//! an orthotropic StVK membrane and dihedral bending solved quasi-statically to equilibrium
//! (`cloth`), its parameters γ = (C00, C11, C01, C22, b) in SI and the paper's CGS units
//! (`material`), contact with a rigid ledge (`contact`), the phase-free DFT shape descriptor of Eq. 9 (`descriptor`) and a
//! box-constrained Levenberg–Marquardt solver (`lm`), the equilibrium's Newton polish and
//! implicit-function derivatives (`equilibrium`), the equilibrium as a differentiable Burn op
//! (`op`) and the Adam fit through it (`adam`), the loading scenarios (`scenario`), the registration of scans to the template
//! (`registration`), targets
//! solved by the FEM source's cloth instead (`fem_target`), and the
//! sim-to-sim estimation of `springtime xpbd estimate` (`estimate`) and the descriptor study of
//! `springtime xpbd descriptors` (`study`).
#![warn(missing_docs)]

pub mod adam;
pub mod cloth;
pub mod contact;
pub mod descriptor;
pub mod equilibrium;
pub mod estimate;
pub mod fem_target;
pub mod lm;
pub mod material;
pub mod op;
pub mod registration;
pub mod scenario;
pub mod study;

pub use cloth::{Equilibrium, Load, Solve, Sweep, XpbdCloth};
pub use material::Gamma;
