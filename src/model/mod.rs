//! Learnable cloth models. The mass-spring surrogate lives in [`springs`].

pub mod kernels;
pub mod springs;

pub use springs::{Kernel, SpringGraph, SpringNet, spring_forces};
