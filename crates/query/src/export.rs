//! The selected Gaussians as a Gaussian set of their own (for `query --export-ply`, which
//! hands it to scene-io's INRIA PLY writer).

use profuse_formats::Gaussians;

use crate::error::{QueryError, Result};

/// The Gaussians `ids` of `gaussians` (in the order given, normally strictly increasing as
/// in a selection), every per-Gaussian field copied bit for bit: means, scales, rotations,
/// opacities, SH coefficients and class ids; the metadata is kept.
pub fn selected_gaussians(gaussians: &Gaussians, ids: &[u32]) -> Result<Gaussians> {
    let n = gaussians.len();
    if let Some(&id) = ids.iter().find(|&&id| id as usize >= n) {
        return Err(QueryError::SelectionOutOfRange { id, count: n });
    }
    let pick = |g: usize| ids.iter().map(move |&i| i as usize).map(move |i| i * g);
    let rest = gaussians.sh_rest.as_ref().map(|r| {
        let per = gaussians.sh_rest_coeffs() * 3;
        pick(per)
            .flat_map(|start| r[start..start + per].iter().copied())
            .collect::<Vec<f32>>()
            .into()
    });
    Ok(Gaussians {
        means: ids
            .iter()
            .map(|&i| gaussians.means[i as usize])
            .collect::<Vec<_>>()
            .into(),
        log_scales: ids
            .iter()
            .map(|&i| gaussians.log_scales[i as usize])
            .collect::<Vec<_>>()
            .into(),
        rotations: ids
            .iter()
            .map(|&i| gaussians.rotations[i as usize])
            .collect::<Vec<_>>()
            .into(),
        opacity_logits: ids
            .iter()
            .map(|&i| gaussians.opacity_logits[i as usize])
            .collect::<Vec<_>>()
            .into(),
        sh_dc: ids
            .iter()
            .map(|&i| gaussians.sh_dc[i as usize])
            .collect::<Vec<_>>()
            .into(),
        sh_degree: gaussians.sh_degree,
        sh_rest: rest,
        class_ids: gaussians.class_ids.as_ref().map(|c| {
            ids.iter()
                .map(|&i| c[i as usize])
                .collect::<Vec<_>>()
                .into()
        }),
        extra: gaussians.extra.clone(),
    })
}
