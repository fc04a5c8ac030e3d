//! alignist: orientation distributions over SO(3) from images of known objects, trained with
//! dense, symmetry-aware targets from CAD experts (Alignist, ECCV 2024).
//!
//! `docs/DESIGN.md` holds the conventions every module shares, the method as implemented, the
//! layout and the bundle format; code cites it by section.

#![warn(missing_docs)]

pub mod backend;
pub mod bench;
pub mod bundle;
pub mod cad;
pub mod client;
pub mod data;
pub mod encoding;
pub mod engine;
pub mod experts;
pub mod net;
pub mod schedule;
pub mod serve;
pub mod so3;
pub mod train;
pub mod viz;
