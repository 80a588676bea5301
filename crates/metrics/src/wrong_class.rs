//! Wrong-class pixel share: how many mask pixels register a descriptor that names the
//! wrong class — the per-pixel semantics a registration hands to the Gaussians, scored
//! before any rendering, selection threshold or PQ.
//!
//! For every pixel of the masks file that carries a mask and whose ground-truth object
//! exists (`object_ids` of synth's `gt/views.safetensors` is not 4294967295), the pixel's
//! class is its object's class (`gt/scene.json`), and the *predicted* class is the best
//! class prompt of the descriptor its mask registers: the argmax of the cosine over the
//! prompts with a class id (`class_ids >= 0`; distractors and canonical negatives do not
//! compete), ties to the lowest prompt index. The pixel is wrong when the two differ.
//!
//! * What a mask registers is an input (`registered`, one entry per global mask): with 3D
//!   Context Proposals the descriptor of the proposal the mask belongs to, for the
//!   `--no-proposals` baseline the mask's own feature (`profuse_fuse::
//!   registered_mask_descriptors` gives both).
//! * A mask that registers nothing (`None`: an orphan under the default `ignore` policy,
//!   or a group without mass) gives its pixels no semantics, so its pixels count as
//!   **wrong** (and are also counted in `unregistered_pixels`).
//! * A pixel whose object's class has no class prompt can never be right; it counts as
//!   wrong too (synth writes a prompt for every class present, so this does not occur on
//!   synthetic scenes).
//! * Pixels without a mask or without an object are not counted at all.

use profuse_formats::{Masks, Prompts, ViewMaps};
use serde::Serialize;

use crate::{invalid, MetricsError, Result};

/// The share and its counts.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct WrongClassShare {
    /// `wrong / pixels` (0 when `pixels` is 0).
    pub share: f64,
    /// Counted pixels: with a mask and a ground-truth object.
    pub pixels: u64,
    /// Counted pixels whose registered class is not their object's class (unregistered
    /// pixels included).
    pub wrong: u64,
    /// Counted pixels whose mask registers nothing.
    pub unregistered_pixels: u64,
    /// Masks that register nothing.
    pub unregistered_masks: usize,
}

/// The class ids of the class prompts with their unit embeddings (f64).
fn class_prompts(prompts: &Prompts, label: &str) -> Result<Vec<(u32, Vec<f64>)>> {
    let Some(ids) = &prompts.class_ids else {
        return Err(invalid(
            label,
            "class_ids",
            "absent: the wrong-class share needs prompts with class ids",
        ));
    };
    let d = prompts.dim;
    let mut out = Vec::new();
    for (q, id) in ids.iter().enumerate() {
        let Ok(class) = u32::try_from(*id) else {
            continue;
        };
        let row = prompts
            .embeddings
            .get(q * d..(q + 1) * d)
            .ok_or_else(|| invalid(label, "embeddings", format!("no row {q}")))?;
        let norm = row
            .iter()
            .map(|x| f64::from(*x) * f64::from(*x))
            .sum::<f64>()
            .sqrt();
        if !(norm > 0.0 && norm.is_finite()) {
            return Err(invalid(
                label,
                format!("embeddings[{q}]"),
                "zero or not finite",
            ));
        }
        out.push((class, row.iter().map(|x| f64::from(*x) / norm).collect()));
    }
    if out.is_empty() {
        return Err(invalid(
            label,
            "class_ids",
            "no prompt has a class id (all -1)",
        ));
    }
    Ok(out)
}

/// The predicted class of every registered descriptor: the class id of the class prompt
/// with the largest cosine (ties: lowest prompt index); `None` where nothing is registered.
/// `prompts_label` names the prompts in errors (the file path).
pub fn mask_classes(
    registered: &[Option<Vec<f32>>],
    prompts: &Prompts,
    prompts_label: &str,
) -> Result<Vec<Option<u32>>> {
    let classes = class_prompts(prompts, prompts_label)?;
    registered
        .iter()
        .enumerate()
        .map(|(m, r)| {
            let Some(f) = r else {
                return Ok(None);
            };
            if f.len() != prompts.dim {
                return Err(invalid(
                    prompts_label,
                    "embeddings",
                    format!(
                        "dimension {}, but the descriptor of mask {m} has {}",
                        prompts.dim,
                        f.len()
                    ),
                ));
            }
            let mut best: Option<(f64, u32)> = None;
            for (class, p) in &classes {
                let cos: f64 = p.iter().zip(f).map(|(a, b)| a * f64::from(*b)).sum();
                if best.is_none_or(|(b, _)| cos > b) {
                    best = Some((cos, *class));
                }
            }
            Ok(best.map(|(_, c)| c))
        })
        .collect()
}

/// Reads the class id of every object of `gt/scene.json` (index = object id of
/// `gt/views.safetensors`), through the typed reader of `profuse-formats`.
pub fn read_object_classes(path: impl AsRef<std::path::Path>) -> Result<Vec<u32>> {
    Ok(profuse_formats::ground_truth::SceneTruth::read(path)?.object_classes())
}

/// The wrong-class pixel share (see the module documentation) of `masks` with ground-truth
/// `objects` (`object_ids` on the masks' grid and views), object classes `object_class`
/// (index = object id) and the predicted class of every global mask's registration
/// (`mask_class`, from [`mask_classes`]). `views_label` names the view maps in errors.
pub fn wrong_class_pixel_share(
    masks: &Masks,
    objects: &ViewMaps,
    views_label: &str,
    object_class: &[u32],
    mask_class: &[Option<u32>],
) -> Result<WrongClassShare> {
    let ids = check_inputs(masks, objects, views_label, mask_class)?;
    let plane = masks.width * masks.height;
    let (mut pixels, mut wrong, mut unregistered_pixels) = (0u64, 0u64, 0u64);
    for v in 0..masks.num_views() {
        for i in v * plane..(v + 1) * plane {
            let Some(local) = masks.labels.get(i) else {
                continue;
            };
            let Some(&object) = ids.get(i) else {
                continue;
            };
            if object == u32::MAX {
                continue;
            }
            let m = (masks.mask_offsets[v] + local) as usize;
            let predicted = mask_class.get(m).ok_or_else(|| {
                invalid(
                    "masks",
                    "labels",
                    format!(
                        "view {v} pixel {} names mask {m} of {}",
                        i - v * plane,
                        mask_class.len()
                    ),
                )
            })?;
            let class = object_class.get(object as usize).ok_or_else(|| {
                invalid(
                    views_label,
                    "object_ids",
                    format!(
                        "object {object}, but the scene has {} objects",
                        object_class.len()
                    ),
                )
            })?;
            pixels += 1;
            match predicted {
                None => {
                    unregistered_pixels += 1;
                    wrong += 1;
                }
                Some(c) if c != class => wrong += 1,
                Some(_) => {}
            }
        }
    }
    Ok(WrongClassShare {
        share: if pixels == 0 {
            0.0
        } else {
            wrong as f64 / pixels as f64
        },
        pixels,
        wrong,
        unregistered_pixels,
        unregistered_masks: mask_class.iter().filter(|c| c.is_none()).count(),
    })
}

/// The checks of [`wrong_class_pixel_share`]: the view maps have object ids on the masks'
/// grid and views, and `mask_class` has one entry per mask. Returns the object ids.
fn check_inputs<'a>(
    masks: &Masks,
    objects: &'a ViewMaps,
    views_label: &str,
    mask_class: &[Option<u32>],
) -> Result<&'a [u32]> {
    let Some(ids) = objects.object_ids.as_deref() else {
        return Err(invalid(views_label, "object_ids", "absent"));
    };
    if (objects.width, objects.height) != (masks.width, masks.height) {
        return Err(invalid(
            views_label,
            "object_ids",
            format!(
                "grid {}x{}, but the masks' grid is {}x{}",
                objects.width, objects.height, masks.width, masks.height
            ),
        ));
    }
    if objects.view_names != masks.view_names {
        return Err(invalid(
            views_label,
            "view_names",
            format!(
                "{} views, not the masks' {} views in the same order",
                objects.view_names.len(),
                masks.view_names.len()
            ),
        ));
    }
    if ids.len() != objects.view_names.len() * objects.width * objects.height {
        return Err(invalid(
            views_label,
            "object_ids",
            format!(
                "{} values, expected {} views x {}x{}",
                ids.len(),
                objects.view_names.len(),
                objects.width,
                objects.height
            ),
        ));
    }
    if mask_class.len() != masks.num_masks() {
        return Err(MetricsError::LengthMismatch {
            what: "wrong-class share",
            left_name: "registered masks",
            left: mask_class.len(),
            right_name: "masks",
            right: masks.num_masks(),
        });
    }
    Ok(ids)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use std::collections::BTreeMap;

    use profuse_formats::{Floats, Labels};

    use super::*;

    /// Two 3x2 views, masks 0..2 in view 0 and 2..4 in view 1; objects 0 (class 5),
    /// 1 (class 7), 2 (class 9).
    fn case() -> (Masks, ViewMaps, Vec<u32>, Prompts) {
        const N: u16 = u16::MAX;
        #[rustfmt::skip]
        let labels: Vec<u16> = vec![
            0, 0, 1,
            N, 1, 1,
            // view 1
            0, 1, 1,
            0, N, 1,
        ];
        #[rustfmt::skip]
        let object_ids: Vec<u32> = vec![
            0, 0, 1,
            0, 1, u32::MAX,
            // view 1
            2, 2, 1,
            0, 1, 1,
        ];
        let names = vec!["a".to_string(), "b".to_string()];
        let masks = Masks {
            view_names: names.clone(),
            width: 3,
            height: 2,
            labels: Labels::U16(labels.into()),
            mask_offsets: vec![0u32, 2, 4].into(),
            features: Floats::F32(vec![1.0f32; 4 * 3].into()),
            dim: 3,
            extra: BTreeMap::new(),
        };
        let views = ViewMaps {
            view_names: names,
            num_objects: 3,
            width: 3,
            height: 2,
            depth: vec![1.0f32; 12].into(),
            object_ids: Some(object_ids.into()),
            extra: BTreeMap::new(),
        };
        // Class prompts 5, 7, 9 along the axes (scaled: consumers normalise), plus a
        // distractor (-1) that would win every cosine if it competed.
        let prompts = Prompts {
            names: ["five", "seven", "nine", "distractor"]
                .map(String::from)
                .to_vec(),
            dim: 3,
            embeddings: vec![
                2.0f32, 0.0, 0.0, //
                0.0, 1.0, 0.0, //
                0.0, 0.0, 3.0, //
                1.0, 1.0, 1.0,
            ]
            .into(),
            class_ids: Some(vec![5i32, 7, 9, -1].into()),
            extra: BTreeMap::new(),
        };
        (masks, views, vec![5, 7, 9], prompts)
    }

    /// The definition, pixel by pixel, with the cosine against every class prompt.
    fn brute_force(
        masks: &Masks,
        views: &ViewMaps,
        object_class: &[u32],
        prompts: &Prompts,
        registered: &[Option<Vec<f32>>],
    ) -> (u64, u64) {
        let ids = views.object_ids.as_ref().unwrap();
        let (mut pixels, mut wrong) = (0, 0);
        for v in 0..masks.num_views() {
            for y in 0..masks.height {
                for x in 0..masks.width {
                    let Some(m) = masks.mask_at(v, x, y) else {
                        continue;
                    };
                    let obj = ids[views.index(v, x, y)];
                    if obj == u32::MAX {
                        continue;
                    }
                    pixels += 1;
                    let truth = object_class[obj as usize];
                    let Some(f) = &registered[m as usize] else {
                        wrong += 1;
                        continue;
                    };
                    let mut best = (f64::NEG_INFINITY, -1);
                    for q in 0..prompts.len() {
                        let class = prompts.class_ids.as_ref().unwrap()[q];
                        if class < 0 {
                            continue;
                        }
                        let p = &prompts.embeddings[q * 3..q * 3 + 3];
                        let dot: f64 = p.iter().zip(f).map(|(a, b)| f64::from(a * b)).sum();
                        let np = p.iter().map(|a| f64::from(a * a)).sum::<f64>().sqrt();
                        let nf = f.iter().map(|a| f64::from(a * a)).sum::<f64>().sqrt();
                        if dot / (np * nf) > best.0 {
                            best = (dot / (np * nf), class);
                        }
                    }
                    if best.1 != truth as i32 {
                        wrong += 1;
                    }
                }
            }
        }
        (pixels, wrong)
    }

    #[test]
    fn matches_the_brute_force_definition_on_a_hand_made_case() {
        let (masks, views, object_class, prompts) = case();
        // Mask 0 -> class 5, mask 1 -> class 7 (its (0.2, 0.9, 0.1) beats the scaled
        // class-5 prompt), mask 2 registers nothing, mask 3 -> class 9.
        let registered = vec![
            Some(vec![0.9, 0.1, 0.0]),
            Some(vec![0.2, 0.9, 0.1]),
            None,
            Some(vec![0.1, 0.2, 0.5]),
        ];
        let classes = mask_classes(&registered, &prompts, "prompts").unwrap();
        assert_eq!(classes, vec![Some(5), Some(7), None, Some(9)]);
        let s = wrong_class_pixel_share(&masks, &views, "views", &object_class, &classes).unwrap();
        let (pixels, wrong) = brute_force(&masks, &views, &object_class, &prompts, &registered);
        assert_eq!((s.pixels, s.wrong), (pixels, wrong));
        // By hand: view 0 counts 4 pixels ((0, 1) has no mask, (2, 1) no object), all
        // right. View 1 counts 5: mask 2 (unregistered) on (0, 0) and (0, 1) is wrong twice;
        // mask 3 (class 9) is right on object 2 at (1, 0) and wrong on object 1 (class 7)
        // at (2, 0) and (2, 1). 4 wrong of 9.
        assert_eq!((s.pixels, s.wrong, s.unregistered_pixels), (9, 4, 2));
        assert_eq!(s.unregistered_masks, 1);
        assert!((s.share - 4.0 / 9.0).abs() < 1e-15);

        // Every mask its own object's class except where masks straddle objects.
        let registered = vec![
            Some(vec![1.0, 0.0, 0.0]),
            Some(vec![0.0, 1.0, 0.0]),
            Some(vec![0.0, 0.0, 1.0]),
            Some(vec![0.0, 1.0, 0.0]),
        ];
        let classes = mask_classes(&registered, &prompts, "prompts").unwrap();
        let s = wrong_class_pixel_share(&masks, &views, "views", &object_class, &classes).unwrap();
        assert_eq!(
            (s.pixels, s.wrong),
            brute_force(&masks, &views, &object_class, &prompts, &registered)
        );
        assert_eq!((s.wrong, s.unregistered_pixels), (2, 0));
    }

    #[test]
    fn mismatched_inputs_are_errors_naming_the_input() {
        let (masks, mut views, object_class, mut prompts) = case();
        let e = wrong_class_pixel_share(&masks, &views, "gt/views", &object_class, &[None])
            .unwrap_err();
        assert!(matches!(e, MetricsError::LengthMismatch { .. }), "{e}");
        views.width = 2;
        let e = wrong_class_pixel_share(&masks, &views, "gt/views", &object_class, &[None; 4])
            .unwrap_err();
        assert!(
            e.to_string().contains("gt/views") && e.to_string().contains("grid"),
            "{e}"
        );
        prompts.class_ids = None;
        let e = mask_classes(&[None], &prompts, "p.safetensors").unwrap_err();
        assert!(e.to_string().contains("p.safetensors"), "{e}");
    }
}
