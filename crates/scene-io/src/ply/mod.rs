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

/// Reads Gaussians from a `profuse.gaussians` file or, by its `.ply` extension, an INRIA
/// 3DGS PLY (with what the PLY reader had to repair; `None` for safetensors).
pub fn read_gaussians(
    path: &std::path::Path,
) -> crate::Result<(profuse_formats::Gaussians, Option<PlyReport>)> {
    use profuse_formats::FileKind;
    let is_ply = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("ply"));
    if is_ply {
        let (g, report) = read_inria_ply(path)?;
        Ok((g, Some(report)))
    } else {
        Ok((profuse_formats::Gaussians::read(path)?, None))
    }
}
