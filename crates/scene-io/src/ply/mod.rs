//! PLY: a strict generic reader ([`read_ply`]) and the INRIA 3DGS Gaussian layout on top
//! of it ([`read_inria_ply`], [`write_inria_ply`]). ScanNet meshes reuse the reader.

mod inria;
mod parser;

pub use inria::{
    gaussians_from_ply, inria_ply_bytes, inria_property_names, read_inria_ply, write_inria_ply,
    PlyReport, OPACITY_LOGIT_CLAMP,
};
pub use parser::{
    parse_header, parse_ply, read_ply, Column, Element, ElementDef, PlyData, PlyFormat, PlyHeader,
    PropertyDef, PropertyType, ScalarType, Values,
};
