//! Learnable cloth models. The mass-spring surrogate lives in [`springs`].

pub mod springs;

pub use springs::{SpringGraph, SpringNet, spring_forces};
