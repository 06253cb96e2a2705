//! bevy_tissue
pub mod core;
