//! Integration tests of the registration against an independent brute-force reference
//! (per pixel, per top-K hit, D-dimensional accumulation in f64, written here), on tiny
//! synthetic scenes whose proposals come from the ground truth.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};

use profuse_formats::{
    Cameras, Container, FileKind, FileWriter, Floats, Gaussians, Kind, Labels, Masks, Proposals,
};
use profuse_fuse::{
    accumulate, dequantise, finish, fuse, group_descriptors, merge, quantise,
    registered_mask_descriptors, FuseError, FuseOptions, Grouping, Groups, MemberWeight, Orphans,
    PartialSums, Precision, Scene, NO_GROUP,
};
use splat_raster::{Rasterizer, RenderOptions, ViewCamera, ViewRender, NO_GAUSSIAN};

/// What each mask's pixels register (`registered_mask_descriptors`), in one test binary
/// with the rest.
mod registered;

/// `err` says that `merge` refused partial files differing in `field`.
fn assert_partial_mismatch(err: &FuseError, field: &str) {
    assert!(
        matches!(err, FuseError::PartialMismatch { field: f, .. } if *f == field),
        "expected a mismatch in {field}, got: {err}"
    );
}

// ---------------------------------------------------------------------------------------
// Fixtures.

struct Fixture {
    _dir: tempfile::TempDir,
    path: PathBuf,
    gaussians: Gaussians,
    cameras: Cameras,
    masks: Masks,
}

/// A tiny synth scene (4 views 64x48, D = 64) with ground-truth Gaussians.
fn tiny(seed: u64, gaussians: usize) -> Fixture {
    tiny_with(seed, gaussians, |_| {})
}

/// [`tiny`] with a change to the synth configuration.
fn tiny_with(seed: u64, gaussians: usize, change: impl FnOnce(&mut synth::Config)) -> Fixture {
    let dir = tempfile::tempdir().unwrap();
    let mut config = synth::Config::preset(synth::Preset::Tiny, seed);
    config.gaussians = gaussians;
    config.write_matches = false;
    change(&mut config);
    synth::generate(&config, dir.path()).unwrap();
    let path = dir.path().to_path_buf();
    Fixture {
        gaussians: Gaussians::read(path.join("gt/gaussians.safetensors")).unwrap(),
        cameras: Cameras::read(path.join("cameras.safetensors")).unwrap(),
        masks: Masks::read(path.join("masks.safetensors")).unwrap(),
        path,
        _dir: dir,
    }
}

/// Proposal groups weighing members by their shares (the default), named `p` in errors.
fn share_groups(masks: &Masks, proposals: &Proposals, orphans: Orphans) -> Groups {
    Groups::from_proposals(masks, proposals, orphans, MemberWeight::Share, "p").unwrap()
}

/// [`Groups::blend`] weighing members by their shares (the default).
fn share_blend(masks: &Masks, proposals: &Proposals, orphans: Orphans) -> Groups {
    Groups::blend(masks, proposals, orphans, MemberWeight::Share, "p").unwrap()
}

impl Fixture {
    fn proposals(&self, min_members: usize) -> Proposals {
        profuse_fuse::testing::proposals_from_mask_objects(
            self.path.join("gt/mask_objects.json"),
            &self.masks,
            min_members,
        )
        .unwrap()
    }

    /// Ground-truth proposals without proposal 0 (the floor): its masks become orphans.
    fn proposals_without_first(&self) -> Proposals {
        let p = self.proposals(1);
        let ids: Vec<u32> = p
            .mask_proposal
            .iter()
            .map(|id| match *id {
                0 | NO_GROUP => NO_GROUP,
                id => id - 1,
            })
            .collect();
        Proposals {
            mask_proposal: ids.into(),
            proposal_size: p.proposal_size[1..].to_vec().into(),
            proposal_views: p.proposal_views[1..].to_vec().into(),
            ..p.clone()
        }
    }

    fn groups_with_orphans(&self, orphans: Orphans) -> Groups {
        share_groups(&self.masks, &self.proposals_without_first(), orphans)
    }

    fn groups(&self, min_members: usize, orphans: Orphans) -> Groups {
        share_groups(&self.masks, &self.proposals(min_members), orphans)
    }

    /// The blend over the proposals of [`Fixture::proposals_without_first`].
    fn blend_groups(&self, orphans: Orphans) -> Groups {
        share_blend(&self.masks, &self.proposals_without_first(), orphans)
    }

    /// The entries of `gt/mask_objects.json`, one per mask.
    fn mask_objects(&self) -> Vec<serde_json::Value> {
        let text = std::fs::read_to_string(self.path.join("gt/mask_objects.json")).unwrap();
        let json: serde_json::Value = serde_json::from_str(&text).unwrap();
        json["masks"].as_array().unwrap().clone()
    }

    /// The ground-truth class of every mask (`class_id` of `gt/mask_objects.json`).
    fn mask_classes(&self) -> Vec<Option<i64>> {
        self.mask_objects()
            .iter()
            .map(|e| e["class_id"].as_i64())
            .collect()
    }

    fn scene(&self) -> Scene<'_> {
        Scene::new(&self.gaussians, &self.cameras, &self.masks)
    }
}

fn f32_opts() -> FuseOptions {
    FuseOptions {
        precision: Some(Precision::F32),
        ..FuseOptions::default()
    }
}

// ---------------------------------------------------------------------------------------
// The brute-force reference.

/// How the reference maps masks to descriptors.
enum RefGroups {
    /// Per mask its proposal (or none); descriptors are mass-weighted pools.
    Pooled(Vec<Option<usize>>),
    /// Every mask registers its own feature.
    Own,
    /// Per mask its proposal (or none), blended with the mask's own feature by
    /// α = clamp(a_m / c_P, 0, 1); orphans register their own feature when the flag is set.
    Blend(Vec<Option<usize>>, bool),
}

struct Reference {
    features: Vec<Option<Vec<f64>>>,
    weight_sum: Vec<f64>,
    mass: Vec<f64>,
    /// The descriptor every mask's pixels register (None: registers nothing).
    mask_desc: Vec<Option<Vec<f64>>>,
}

/// The camera of a view at the mask grid, built from the cameras' rows directly.
fn reference_camera(cameras: &Cameras, v: usize, w: usize, h: usize) -> ViewCamera {
    let m = cameras.world_to_camera[v];
    let [iw, ih] = cameras.image_size[v];
    let [fx, fy, cx, cy] = cameras.intrinsics[v];
    let (sx, sy) = (w as f64 / f64::from(iw), h as f64 / f64::from(ih));
    ViewCamera {
        rotation: [[m[0], m[1], m[2]], [m[4], m[5], m[6]], [m[8], m[9], m[10]]],
        translation: [m[3], m[7], m[11]],
        intrinsics: [fx * sx, fy * sy, cx * sx, cy * sy],
        width: w as u32,
        height: h as u32,
    }
}

/// Eqs. mask-mass, proposal-desc, accumulate and gaussian-feature, literally: every view
/// rendered and kept, then every labelled pixel's every hit adds ω f̄ to A[g] in f64.
fn reference(
    g: &Gaussians,
    cams: &Cameras,
    masks: &Masks,
    groups: &RefGroups,
    k: usize,
) -> Reference {
    reference_weighed(g, cams, masks, groups, k, &[])
}

/// [`reference`] with every hit of a pixel of mask m adding `factor[m]` ω f̄ to A[g] and
/// `factor[m]` ω to S[g] (empty: 1); the masses stay Σ ω.
fn reference_weighed(
    g: &Gaussians,
    cams: &Cameras,
    masks: &Masks,
    groups: &RefGroups,
    k: usize,
    factor: &[f64],
) -> Reference {
    let raster = Rasterizer::new(g).unwrap();
    let opts = RenderOptions {
        color: false,
        top_k: Some(k),
        ..RenderOptions::default()
    };
    let (w, h, d) = (masks.width, masks.height, masks.dim);
    let renders: Vec<ViewRender> = (0..cams.len())
        .map(|v| {
            let mut out = ViewRender::default();
            raster
                .render_camera_into(&reference_camera(cams, v, w, h), v, &opts, &mut out)
                .unwrap();
            out
        })
        .collect();
    let mask_at = |v: usize, x: usize, y: usize| masks.mask_at(v, x, y).map(|m| m as usize);
    let hits = |v: usize, x: usize, y: usize| {
        let (ids, ws) = renders[v].topk(x, y).unwrap();
        ids.iter()
            .zip(ws)
            .filter(|(id, _)| **id != NO_GAUSSIAN)
            .map(|(id, w)| (*id as usize, f64::from(*w)))
            .collect::<Vec<_>>()
    };
    let pixels = || {
        (0..cams.len()).flat_map(move |v| (0..h).flat_map(move |y| (0..w).map(move |x| (v, x, y))))
    };

    let mut mass = vec![0.0; masks.num_masks()];
    for (v, x, y) in pixels() {
        if let Some(m) = mask_at(v, x, y) {
            mass[m] += hits(v, x, y).iter().map(|(_, w)| w).sum::<f64>();
        }
    }
    let feature = |m: usize| -> Vec<f64> {
        (0..d)
            .map(|j| f64::from(masks.features.get(m * d + j)))
            .collect()
    };
    let normalise = |v: &mut Vec<f64>| {
        let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        if n > 0.0 {
            v.iter_mut().for_each(|x| *x /= n);
        }
    };
    let pools = |of: &[Option<usize>]| {
        let p_count = of.iter().flatten().max().map_or(0, |p| p + 1);
        let mut pooled = vec![vec![0.0; d]; p_count];
        for (m, p) in of.iter().enumerate() {
            if let Some(p) = p {
                for (a, f) in pooled[*p].iter_mut().zip(feature(m)) {
                    *a += mass[m] * f;
                }
            }
        }
        pooled.iter_mut().for_each(normalise);
        pooled
    };
    // Descriptor of the pixel's mask.
    let desc_of: Vec<Option<Vec<f64>>> = match groups {
        RefGroups::Own => (0..masks.num_masks())
            .map(|m| {
                let mut f = feature(m);
                normalise(&mut f);
                Some(f)
            })
            .collect(),
        RefGroups::Pooled(of) => {
            let pooled = pools(of);
            of.iter().map(|p| p.map(|p| pooled[p].clone())).collect()
        }
        RefGroups::Blend(of, singleton) => {
            let pooled = pools(of);
            let unit = |m: usize| {
                let mut f = feature(m);
                normalise(&mut f);
                f
            };
            let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
            let agreement: Vec<f64> = (0..masks.num_masks())
                .map(|m| of[m].map_or(0.0, |p| dot(&unit(m), &pooled[p])))
                .collect();
            let mut typical = vec![(0.0, 0.0); pooled.len()];
            for (m, p) in of.iter().enumerate() {
                if let Some(p) = p {
                    typical[*p].0 += mass[m] * agreement[m];
                    typical[*p].1 += mass[m];
                }
            }
            (0..masks.num_masks())
                .map(|m| match of[m] {
                    None => singleton.then(|| unit(m)),
                    Some(p) => {
                        let (num, den) = typical[p];
                        let c = if den > 0.0 { num / den } else { 0.0 };
                        let alpha = if c > 0.0 {
                            (agreement[m] / c).clamp(0.0, 1.0)
                        } else {
                            0.0
                        };
                        let mut out: Vec<f64> = pooled[p]
                            .iter()
                            .zip(unit(m))
                            .map(|(b, o)| alpha * b + (1.0 - alpha) * o)
                            .collect();
                        normalise(&mut out);
                        Some(out)
                    }
                })
                .collect()
        }
    };
    let n = g.len();
    let mut a = vec![vec![0.0; d]; n];
    let mut s = vec![0.0; n];
    for (v, x, y) in pixels() {
        let Some(desc) = mask_at(v, x, y).and_then(|m| desc_of[m].as_ref()) else {
            continue;
        };
        let m = mask_at(v, x, y).unwrap_or(0);
        let scale = factor.get(m).copied().unwrap_or(1.0);
        for (id, w) in hits(v, x, y) {
            let w = w * scale;
            for (ai, fi) in a[id].iter_mut().zip(desc) {
                *ai += w * fi;
            }
            s[id] += w;
        }
    }
    let features = a
        .into_iter()
        .zip(&s)
        .map(|(mut a, s)| {
            if *s == 0.0 {
                return None;
            }
            a.iter_mut().for_each(|x| *x /= s.max(1e-12));
            normalise(&mut a);
            Some(a)
        })
        .collect();
    Reference {
        features,
        weight_sum: s,
        mass,
        mask_desc: desc_of,
    }
}

/// The reference's view of a blend grouping: every mask's proposal.
fn blend_ref(groups: &Groups) -> RefGroups {
    let Grouping::Blend { orphans } = groups.grouping else {
        panic!("not a blend")
    };
    RefGroups::Blend(
        groups
            .mask_proposal
            .iter()
            .map(|p| (*p != NO_GROUP).then_some(*p as usize))
            .collect(),
        orphans == Orphans::Singleton,
    )
}

fn pooled_groups(groups: &Groups) -> RefGroups {
    RefGroups::Pooled(
        groups
            .mask_group
            .iter()
            .map(|p| (*p != NO_GROUP).then_some(*p as usize))
            .collect(),
    )
}

/// Asserts that the registration equals the reference to 1e-5 per component.
fn assert_matches(reg: &profuse_fuse::Registration, r: &Reference) -> usize {
    let f = &reg.features;
    let d = f.dim;
    let Floats::F32(values) = &f.features else {
        panic!("expected F32 features")
    };
    let sums = f.weight_sum.as_ref().unwrap();
    let mut valid = 0;
    for (g, expected) in r.features.iter().enumerate() {
        match expected {
            None => {
                assert_eq!(f.valid[g], 0, "Gaussian {g} should be invalid");
                assert_eq!(sums[g], 0.0);
                assert!(values[g * d..][..d].iter().all(|x| *x == 0.0));
            }
            Some(e) => {
                valid += 1;
                assert_eq!(f.valid[g], 1, "Gaussian {g} should be valid");
                let rel = (f64::from(sums[g]) - r.weight_sum[g]).abs() / r.weight_sum[g];
                assert!(
                    rel < 1e-6,
                    "Gaussian {g}: S {} vs {}",
                    sums[g],
                    r.weight_sum[g]
                );
                for (j, (got, want)) in values[g * d..][..d].iter().zip(e).enumerate() {
                    assert!(
                        (f64::from(*got) - want).abs() < 1e-5,
                        "Gaussian {g} component {j}: {got} vs {want}"
                    );
                }
            }
        }
    }
    assert_eq!(reg.summary.valid, valid);
    valid
}

// ---------------------------------------------------------------------------------------
// Agreement with the reference.

/// Member pixels weighed by s_m^e (`Groups::with_pixel_shares`): W and S are the
/// brute-force sums of ω · s_m^e (factors rounded to 2^-16 as documented), orphans weigh ω,
/// the masses stay Σ ω (the descriptors, pooled by mass, are the paper's), and e = 0 or a
/// file without shares leaves the paper's bytes.
#[test]
fn member_pixels_weighed_by_their_shares_match_the_brute_force_reference() {
    let fx = tiny(3, 9000);
    let mut proposals = fx.proposals_without_first();
    let shares: Vec<f32> = (0..fx.masks.num_masks())
        .map(|m| 0.25 + 0.75 * ((m * 37) % 11) as f32 / 10.0)
        .collect();
    proposals.mask_share = Some(shares.clone().into());
    let power = 2.0;
    let mass_groups = |p: &Proposals| {
        Groups::from_proposals(&fx.masks, p, Orphans::Singleton, MemberWeight::Mass, "p").unwrap()
    };
    let groups = mass_groups(&proposals)
        .with_pixel_shares(&proposals, power)
        .unwrap();
    let orphans = proposals
        .mask_proposal
        .iter()
        .filter(|p| **p == NO_GROUP)
        .count();
    assert!(orphans > 0, "no orphans");
    let factor: Vec<f64> = proposals
        .mask_proposal
        .iter()
        .zip(&shares)
        .map(|(p, s)| {
            if *p == NO_GROUP {
                1.0
            } else {
                (f64::from(*s).powf(power) * 65536.0).round() / 65536.0
            }
        })
        .collect();
    assert!(factor.iter().any(|f| *f < 0.2) && factor.contains(&1.0));
    let reg = fuse(&fx.scene(), &groups, &f32_opts()).unwrap();
    let r = reference_weighed(
        &fx.gaussians,
        &fx.cameras,
        &fx.masks,
        &pooled_groups(&groups),
        10,
        &factor,
    );
    assert!(assert_matches(&reg, &r) > 1000);
    assert_eq!(
        reg.features
            .extra
            .get("pixel_share_power")
            .map(String::as_str),
        Some("2")
    );
    // The weighing changes the features, and e = 0 or no shares give the paper's bytes.
    let paper = fuse(&fx.scene(), &mass_groups(&proposals), &f32_opts()).unwrap();
    assert_ne!(paper.features.features, reg.features.features);
    let zero = mass_groups(&proposals)
        .with_pixel_shares(&proposals, 0.0)
        .unwrap();
    assert!(zero.pixel_weight.is_empty());
    let unshared = fx.proposals_without_first();
    let none = mass_groups(&unshared)
        .with_pixel_shares(&unshared, power)
        .unwrap();
    assert!(none.pixel_weight.is_empty());
    for g in [zero, none] {
        let f = fuse(&fx.scene(), &g, &f32_opts()).unwrap().features;
        assert_eq!(f.features, paper.features.features);
        assert!(!f.extra.contains_key("pixel_share_power"));
    }
    // Negative or non-finite exponents are refused.
    for bad in [-1.0, f64::NAN, f64::INFINITY] {
        let err = mass_groups(&proposals)
            .with_pixel_shares(&proposals, bad)
            .unwrap_err();
        assert!(matches!(err, FuseError::PixelSharePower(_)), "{err}");
    }
}

#[test]
fn proposals_match_the_brute_force_reference() {
    let fx = tiny(3, 9000);
    // The floor's masks are orphans, so the ignore rule is exercised.
    let groups = fx.groups_with_orphans(Orphans::Ignore);
    assert!(groups.mask_group.contains(&NO_GROUP), "no orphans");
    let reg = fuse(&fx.scene(), &groups, &f32_opts()).unwrap();
    let r = reference(
        &fx.gaussians,
        &fx.cameras,
        &fx.masks,
        &pooled_groups(&groups),
        10,
    );
    let valid = assert_matches(&reg, &r);
    // The floor (NYU40 class 2) is an orphan: most floor Gaussians stay invalid, nearly
    // every other one is registered.
    let classes = fx.gaussians.class_ids.as_ref().unwrap();
    let count = |floor: bool, valid: u8| {
        (0..fx.gaussians.len())
            .filter(|g| (classes[*g] == 2) == floor && reg.features.valid[*g] == valid)
            .count()
    };
    let (floor_valid, floor_invalid) = (count(true, 1), count(true, 0));
    let (other_valid, other_invalid) = (count(false, 1), count(false, 0));
    assert!(
        floor_invalid > 3 * floor_valid,
        "{floor_valid} {floor_invalid}"
    );
    assert!(
        other_valid > 8 * other_invalid,
        "{other_valid} {other_invalid}"
    );
    assert_eq!(valid, floor_valid + other_valid);
    // F16 storage rounds the same descriptors.
    let half = FuseOptions {
        precision: Some(Precision::F16),
        ..FuseOptions::default()
    };
    let h = fuse(&fx.scene(), &groups, &half).unwrap().features;
    assert_eq!(h.valid, reg.features.valid);
    let (a, b) = (h.features.to_f32_vec(), reg.features.features.to_f32_vec());
    assert!(a
        .iter()
        .zip(&b)
        .all(|(x, y)| (x - y).abs() <= 1e-3 * y.abs().max(1e-2)));
    // Masses equal the reference's, so mass-weighting is what the paper says.
    let total: f64 = r.mass.iter().sum();
    assert!((reg.summary.mass_total - total).abs() < 1e-9 * total);
    assert!(reg.summary.nnz >= valid && reg.summary.nnz < 3 * valid);
}

#[test]
fn singleton_orphans_and_k_match_the_reference() {
    let fx = tiny(5, 2000);
    let groups = fx.groups_with_orphans(Orphans::Singleton);
    assert!(!groups.mask_group.contains(&NO_GROUP));
    let opts = FuseOptions { k: 4, ..f32_opts() };
    let reg = fuse(&fx.scene(), &groups, &opts).unwrap();
    let r = reference(
        &fx.gaussians,
        &fx.cameras,
        &fx.masks,
        &pooled_groups(&groups),
        4,
    );
    assert_matches(&reg, &r);
    // Singletons register more Gaussians than ignoring the orphans does.
    let ignored = fuse(&fx.scene(), &fx.groups_with_orphans(Orphans::Ignore), &opts).unwrap();
    assert!(reg.summary.valid > ignored.summary.valid);
}

#[test]
fn no_proposals_baseline_matches_the_reference() {
    let fx = tiny(7, 2000);
    let groups = Groups::per_mask(&fx.masks);
    let reg = fuse(&fx.scene(), &groups, &f32_opts()).unwrap();
    let r = reference(&fx.gaussians, &fx.cameras, &fx.masks, &RefGroups::Own, 10);
    assert_matches(&reg, &r);
    assert_eq!(reg.summary.groups, fx.masks.num_masks());
}

/// Masks on a grid coarser than the images (and with U32 labels): the views are rendered
/// at the grid with scaled intrinsics.
#[test]
fn coarser_mask_grid_matches_the_reference() {
    let fx = tiny(11, 3000);
    let (w, h) = (fx.masks.width / 2, fx.masks.height / 2);
    let mut labels = Vec::new();
    for v in 0..fx.masks.num_views() {
        for y in 0..h {
            for x in 0..w {
                let i = (v * fx.masks.height + 2 * y) * fx.masks.width + 2 * x;
                labels.push(fx.masks.labels.get(i).unwrap_or(u32::MAX));
            }
        }
    }
    let coarse = Masks {
        width: w,
        height: h,
        labels: Labels::U32(labels.into()),
        ..fx.masks.clone()
    };
    coarse.validate("coarse").unwrap();
    let groups = fx.groups(1, Orphans::Ignore);
    let scene = Scene::new(&fx.gaussians, &fx.cameras, &coarse);
    let reg = fuse(&scene, &groups, &f32_opts()).unwrap();
    let r = reference(
        &fx.gaussians,
        &fx.cameras,
        &coarse,
        &pooled_groups(&groups),
        10,
    );
    let valid = assert_matches(&reg, &r);
    assert!(valid > 1000, "{valid}");
    // A quarter of the pixels: the mass is about a quarter of the full grid's.
    let full = fuse(&fx.scene(), &groups, &f32_opts()).unwrap();
    let ratio = reg.summary.mass_total / full.summary.mass_total;
    assert!((0.2..0.3).contains(&ratio), "mass ratio {ratio}");
}

/// Share of the valid Gaussians (with a ground-truth class) whose descriptor is closest to
/// the feature centroid of their own class (centroids of the masks by dominant class).
fn class_accuracy(fx: &Fixture, reg: &profuse_fuse::Registration) -> f64 {
    let json: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(fx.path.join("gt/mask_objects.json")).unwrap(),
    )
    .unwrap();
    let d = fx.masks.dim;
    let mut centroids: std::collections::BTreeMap<i64, Vec<f64>> = Default::default();
    for (m, e) in json["masks"].as_array().unwrap().iter().enumerate() {
        if let Some(c) = e["class_id"].as_i64() {
            let row = centroids.entry(c).or_insert_with(|| vec![0.0; d]);
            for (j, r) in row.iter_mut().enumerate() {
                *r += f64::from(fx.masks.features.get(m * d + j));
            }
        }
    }
    let classes = fx.gaussians.class_ids.as_ref().unwrap();
    let (mut right, mut total) = (0, 0);
    for g in 0..fx.gaussians.len() {
        if reg.features.valid[g] == 0 || classes[g] < 0 {
            continue;
        }
        let f: Vec<f64> = (0..d)
            .map(|j| f64::from(reg.features.features.get(g * d + j)))
            .collect();
        let best = centroids
            .iter()
            .map(|(c, v)| {
                let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
                (v.iter().zip(&f).map(|(a, b)| a * b).sum::<f64>() / n, *c)
            })
            .max_by(|a, b| a.0.total_cmp(&b.0))
            .unwrap()
            .1;
        total += 1;
        right += usize::from(best == i64::from(classes[g]));
    }
    assert!(total > fx.gaussians.len() / 2, "{total}");
    right as f64 / total as f64
}

/// The registered descriptors carry the right semantics: most Gaussians are closest to
/// the feature centroid of their own ground-truth class.
#[test]
fn gaussians_get_their_own_class() {
    let fx = tiny(14, 3000);
    let reg = fuse(&fx.scene(), &fx.groups(1, Orphans::Ignore), &f32_opts()).unwrap();
    let base = fuse(&fx.scene(), &Groups::per_mask(&fx.masks), &f32_opts()).unwrap();
    // A wrong Gaussian-to-descriptor assignment would score about 1 / (classes = 8).
    let (ours, baseline) = (class_accuracy(&fx, &reg), class_accuracy(&fx, &base));
    assert!(ours > 0.9 && baseline > 0.85, "{ours} {baseline}");
}

// ---------------------------------------------------------------------------------------
// The blend registration (`Grouping::Blend`).

/// Asserts that the per-mask descriptors equal the reference's to 1e-6 per component (a
/// reference descriptor of zeros registers nothing, like `None`).
fn assert_mask_descriptors(got: &[Option<Vec<f32>>], r: &Reference) {
    assert_eq!(got.len(), r.mask_desc.len());
    for (m, (got, want)) in got.iter().zip(&r.mask_desc).enumerate() {
        let want = want.as_ref().filter(|w| w.iter().any(|x| *x != 0.0));
        match (got, want) {
            (None, None) => {}
            (Some(g), Some(w)) => {
                for (j, (a, b)) in g.iter().zip(w).enumerate() {
                    assert!(
                        (f64::from(*a) - b).abs() < 1e-6,
                        "mask {m} component {j}: {a} vs {b}"
                    );
                }
            }
            _ => panic!("mask {m}: {:?} vs {:?}", got.is_some(), want.is_some()),
        }
    }
}

/// The blend's per-mask descriptors d_m and the per-Gaussian features equal a
/// brute-force reference (the literal formula on the reference's masses), with orphans
/// ignored and, at K = 4, registering their own features.
#[test]
fn blend_matches_the_brute_force_reference() {
    let fx = tiny(3, 9000);
    for (orphans, k) in [(Orphans::Ignore, 10), (Orphans::Singleton, 4)] {
        let groups = fx.blend_groups(orphans);
        assert_eq!(groups.num_groups, fx.masks.num_masks());
        let opts = FuseOptions { k, ..f32_opts() };
        let reg = fuse(&fx.scene(), &groups, &opts).unwrap();
        let r = reference(
            &fx.gaussians,
            &fx.cameras,
            &fx.masks,
            &blend_ref(&groups),
            k,
        );
        assert_matches(&reg, &r);
        let partial = accumulate(&fx.scene(), &groups, k, 0..4, &mut |_| {}).unwrap();
        assert_mask_descriptors(&registered_mask_descriptors(&partial), &r);
        assert_eq!(reg.features.extra["grouping"], "blend");
        assert_eq!(reg.features.extra["orphans"], orphans.name());
        // The blend is not trivial here: some masks keep their proposal's descriptor,
        // others get a mix.
        let paper = share_groups(&fx.masks, &fx.proposals_without_first(), orphans);
        let pooled = registered_mask_descriptors(
            &accumulate(&fx.scene(), &paper, k, 0..4, &mut |_| {}).unwrap(),
        );
        let blended = registered_mask_descriptors(&partial);
        let in_proposal = |m: &usize| groups.mask_proposal[*m] != NO_GROUP;
        let same = (0..pooled.len())
            .filter(in_proposal)
            .filter(|m| pooled[*m] == blended[*m])
            .count();
        let members = (0..pooled.len()).filter(in_proposal).count();
        assert!(same > 0 && same < members, "{same} of {members}");
    }
}

/// Replaces the features of `masks` (F32).
fn with_features(masks: &Masks, features: Vec<f32>) -> Masks {
    Masks {
        features: Floats::F32(features.into()),
        ..masks.clone()
    }
}

/// When every member of a proposal has the same feature direction, every mask is as
/// coherent as its proposal's average member: the blend registers the paper's descriptors,
/// and the files' tensors have the paper's bytes (W's mask columns add up to the paper's
/// proposal columns exactly).
#[test]
fn coherent_proposals_blend_to_the_paper_bytes() {
    let fx = tiny(5, 3000);
    let (d, m_count) = (fx.masks.dim, fx.masks.num_masks());
    let p = fx.proposals_without_first();
    // Per proposal its first member's feature, scaled differently per member (the
    // direction is what counts); orphans keep theirs.
    let old = fx.masks.features.to_f32_vec();
    let mut first: std::collections::BTreeMap<u32, usize> = Default::default();
    let mut features = old.clone();
    for m in 0..m_count {
        let id = p.mask_proposal[m];
        if id == NO_GROUP {
            continue;
        }
        let src = *first.entry(id).or_insert(m);
        let scale = [1.0, 0.5, 2.0, 0.75][m % 4];
        for j in 0..d {
            features[m * d + j] = scale * old[src * d + j];
        }
    }
    let masks = with_features(&fx.masks, features);
    let scene = Scene::new(&fx.gaussians, &fx.cameras, &masks);
    for orphans in [Orphans::Ignore, Orphans::Singleton] {
        let paper = share_groups(&masks, &p, orphans);
        let blend = share_blend(&masks, &p, orphans);
        let a = fuse(&scene, &paper, &f32_opts()).unwrap();
        let b = fuse(&scene, &blend, &f32_opts()).unwrap();
        assert_eq!(a.features.features, b.features.features, "{orphans:?}");
        assert_eq!(a.features.valid, b.features.valid);
        assert_eq!(a.features.weight_sum, b.features.weight_sum);
        assert!(b.summary.nnz > a.summary.nnz, "W's groups are the masks");
    }
}

/// A mask whose feature is orthogonal to its proposal's descriptor (a_m = 0) registers
/// its own feature (the per-mask baseline's descriptor); one pointing away (a_m < 0) too,
/// exactly.
#[test]
fn a_mask_orthogonal_to_its_proposal_keeps_its_own_feature() {
    let fx = tiny(7, 2000);
    let (d, m_count) = (fx.masks.dim, fx.masks.num_masks());
    let groups = share_blend(&fx.masks, &fx.proposals(1), Orphans::Ignore);
    let scene = fx.scene();
    // Masses do not depend on the features: take them from one pass.
    let mass: Vec<f64> = accumulate(&scene, &groups, 10, 0..4, &mut |_| {})
        .unwrap()
        .mask_mass()
        .iter()
        .map(|q| dequantise(*q))
        .collect();
    // The proposal with the most mass; its heaviest member `m0` is made orthogonal, the
    // others all get e_0. f̄ ∝ S e_0 + μ_0 (e_1 + x e_0), orthogonal to e_1 + x e_0 when
    // μ_0 x² + S x + μ_0 = 0.
    let prop = groups.mask_proposal.clone();
    let mut by_mass: Vec<usize> = (0..m_count).filter(|m| prop[*m] != NO_GROUP).collect();
    by_mass.sort_by(|a, b| mass[*b].total_cmp(&mass[*a]));
    let target = prop[by_mass[0]];
    let members: Vec<usize> = (0..m_count).filter(|m| prop[*m] == target).collect();
    let m0 = *members
        .iter()
        .filter(|m| mass[**m] > 0.0)
        .min_by(|a, b| mass[**a].total_cmp(&mass[**b]))
        .unwrap();
    let s: f64 = members.iter().filter(|m| **m != m0).map(|m| mass[*m]).sum();
    let mu = mass[m0];
    assert!(s > 2.0 * mu, "{s} {mu}");
    let x = (-s + (s * s - 4.0 * mu * mu).sqrt()) / (2.0 * mu);
    let mut features = fx.masks.features.to_f32_vec();
    for m in &members {
        let row = &mut features[m * d..][..d];
        row.fill(0.0);
        if *m == m0 {
            row[0] = x as f32;
            row[1] = 1.0;
        } else {
            row[0] = 1.0;
        }
    }
    let own = |features: &[f32], m: usize| -> Vec<f32> {
        let row: Vec<f64> = features[m * d..][..d]
            .iter()
            .map(|v| f64::from(*v))
            .collect();
        let n = row.iter().map(|v| v * v).sum::<f64>().sqrt();
        row.iter().map(|v| (v / n) as f32).collect()
    };
    let masks = with_features(&fx.masks, features.clone());
    let scene = Scene::new(&fx.gaussians, &fx.cameras, &masks);
    let partial = accumulate(&scene, &groups, 10, 0..4, &mut |_| {}).unwrap();
    let got = registered_mask_descriptors(&partial)[m0].clone().unwrap();
    let want = own(&features, m0);
    assert!(
        got.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-6),
        "{got:?} vs {want:?}"
    );
    // The other members are more coherent than average: they keep f̄_P.
    let desc = profuse_fuse::group_descriptors(&partial);
    let paper = share_groups(&masks, &fx.proposals(1), Orphans::Ignore);
    let paper_desc =
        registered_mask_descriptors(&accumulate(&scene, &paper, 10, 0..4, &mut |_| {}).unwrap());
    let other = members
        .iter()
        .find(|m| **m != m0 && mass[**m] > 0.0)
        .unwrap();
    assert_eq!(
        registered_mask_descriptors(&partial)[*other],
        paper_desc[*other]
    );
    assert_eq!(desc.len(), m_count * d);

    // Pointing away from the proposal: α = 0, exactly its own normalised feature.
    features[m0 * d] = -1.0;
    features[m0 * d + 1] = 0.25;
    let masks = with_features(&fx.masks, features.clone());
    let scene = Scene::new(&fx.gaussians, &fx.cameras, &masks);
    let partial = accumulate(&scene, &groups, 10, 0..4, &mut |_| {}).unwrap();
    let baseline = accumulate(&scene, &Groups::per_mask(&masks), 10, 0..4, &mut |_| {}).unwrap();
    assert_eq!(
        registered_mask_descriptors(&partial)[m0],
        registered_mask_descriptors(&baseline)[m0]
    );
}

/// Dense proposals from per-mask ids (sizes and view counts recomputed; unused ids
/// dropped, order kept).
fn proposals_from_ids(masks: &Masks, ids: &[u32], like: &Proposals) -> Proposals {
    let mut used: Vec<u32> = ids.iter().copied().filter(|i| *i != NO_GROUP).collect();
    used.sort_unstable();
    used.dedup();
    let dense: Vec<u32> = ids
        .iter()
        .map(|i| match used.binary_search(i) {
            Ok(r) => r as u32,
            Err(_) => NO_GROUP,
        })
        .collect();
    let mut sizes = vec![0u32; used.len()];
    let mut views: Vec<Vec<usize>> = vec![Vec::new(); used.len()];
    for (m, p) in dense.iter().enumerate() {
        if *p != NO_GROUP {
            sizes[*p as usize] += 1;
            views[*p as usize].push(masks.view_of(m));
        }
    }
    Proposals {
        mask_proposal: dense.into(),
        proposal_size: sizes.into(),
        proposal_views: views
            .into_iter()
            .map(|mut v| {
                v.dedup();
                v.len() as u32
            })
            .collect::<Vec<_>>()
            .into(),
        ..like.clone()
    }
}

/// An impure proposal: the masks of object B (a minority of the mass) wrongly joined to
/// the proposal of object A. The paper's rule gives B's pixels A's class; the blend keeps
/// B's own class, for its masks and for B's Gaussians. The masks' features are coherent
/// (noisy, but no mask merged across objects or pulled toward another class), which is
/// what lets the blend tell B's masks from A's.
#[test]
fn an_impure_proposal_does_not_poison_its_minority_under_blend() {
    let fx = tiny_with(14, 3000, |c| {
        c.faults.p_merge = 0.0;
        c.faults.p_wrong_class = 0.0;
    });
    let d = fx.masks.dim;
    let class_of_mask = fx.mask_classes();
    let p = fx.proposals(1);
    let groups = share_groups(&fx.masks, &p, Orphans::Ignore);
    let mass: Vec<f64> = accumulate(&fx.scene(), &groups, 10, 0..4, &mut |_| {})
        .unwrap()
        .mask_mass()
        .iter()
        .map(|q| dequantise(*q))
        .collect();
    // Per proposal: its mass and its (dominant) class.
    let count = p.len();
    let mut prop_mass = vec![0.0; count];
    let mut prop_class = vec![None; count];
    for (m, id) in p.mask_proposal.iter().enumerate() {
        if *id != NO_GROUP {
            prop_mass[*id as usize] += mass[m];
            prop_class[*id as usize] = prop_class[*id as usize].or(class_of_mask[m]);
        }
    }
    let unique = |c: Option<i64>| prop_class.iter().filter(|x| **x == c).count() == 1;
    let a = (0..count)
        .max_by(|x, y| prop_mass[*x].total_cmp(&prop_mass[*y]))
        .unwrap();
    // B: the heaviest proposal of another class that is still a minority (< 40%).
    let b = (0..count)
        .filter(|b| *b != a && unique(prop_class[*b]) && prop_class[*b] != prop_class[a])
        .filter(|b| prop_mass[*b] < 0.4 * (prop_mass[a] + prop_mass[*b]))
        .max_by(|x, y| prop_mass[*x].total_cmp(&prop_mass[*y]))
        .unwrap();
    let share = prop_mass[b] / (prop_mass[a] + prop_mass[b]);
    assert!(share > 0.1, "B's share of the mass {share}");
    let (class_a, class_b) = (prop_class[a].unwrap(), prop_class[b].unwrap());
    let ids: Vec<u32> = p
        .mask_proposal
        .iter()
        .map(|id| if *id == b as u32 { a as u32 } else { *id })
        .collect();
    let impure = proposals_from_ids(&fx.masks, &ids, &p);
    let b_masks: Vec<usize> = (0..ids.len())
        .filter(|m| p.mask_proposal[*m] == b as u32 && mass[*m] > 0.0)
        .collect();
    assert!(b_masks.len() >= 2);

    // Class centroids of the mask features.
    let centroid = |class: i64| {
        let mut c = vec![0.0f64; d];
        for (m, cm) in class_of_mask.iter().enumerate() {
            if *cm == Some(class) {
                for (j, x) in c.iter_mut().enumerate() {
                    *x += f64::from(fx.masks.features.get(m * d + j));
                }
            }
        }
        let n = c.iter().map(|x| x * x).sum::<f64>().sqrt();
        c.iter().map(|x| x / n).collect::<Vec<f64>>()
    };
    let (ca, cb) = (centroid(class_a), centroid(class_b));
    let closer_to_b = |f: &[f64]| {
        let dot = |c: &[f64]| c.iter().zip(f).map(|(x, y)| x * y).sum::<f64>();
        dot(&cb) > dot(&ca)
    };
    let classes = fx.gaussians.class_ids.as_ref().unwrap();
    let run = |groups: &Groups| {
        let partial = accumulate(&fx.scene(), groups, 10, 0..4, &mut |_| {}).unwrap();
        let desc = registered_mask_descriptors(&partial);
        let masks_b = b_masks
            .iter()
            .filter(|m| {
                let f: Vec<f64> = desc[**m]
                    .as_ref()
                    .unwrap()
                    .iter()
                    .map(|x| f64::from(*x))
                    .collect();
                closer_to_b(&f)
            })
            .count();
        let reg = finish(&partial, Precision::F32);
        let (mut right, mut total) = (0, 0);
        for g in 0..fx.gaussians.len() {
            if reg.features.valid[g] == 1 && i64::from(classes[g]) == class_b {
                let f: Vec<f64> = (0..d)
                    .map(|j| f64::from(reg.features.features.get(g * d + j)))
                    .collect();
                total += 1;
                right += usize::from(closer_to_b(&f));
            }
        }
        assert!(total > 20, "{total} Gaussians of B");
        (masks_b, right as f64 / total as f64)
    };
    let paper = share_groups(&fx.masks, &impure, Orphans::Ignore);
    let blend = share_blend(&fx.masks, &impure, Orphans::Ignore);
    let (paper_masks, paper_gaussians) = run(&paper);
    let (blend_masks, blend_gaussians) = run(&blend);
    let n = b_masks.len();
    assert_eq!(paper_masks, 0, "the paper gives B's masks A's descriptor");
    assert_eq!(blend_masks, n, "the blend keeps B's masks with B");
    assert!(
        paper_gaussians < 0.2 && blend_gaussians > 0.8,
        "B's Gaussians closer to B: paper {paper_gaussians}, blend {blend_gaussians} \
         (B's share of the mass {share})"
    );
}

// ---------------------------------------------------------------------------------------
// Sharding, determinism, memory.

fn bytes(reg: &profuse_fuse::Registration, dir: &Path, name: &str) -> Vec<u8> {
    let p = dir.join(name);
    reg.features.write(&p).unwrap();
    std::fs::read(p).unwrap()
}

#[test]
fn sharded_partial_files_merge_to_the_unsharded_bytes() {
    let fx = tiny(17, 9000);
    let dir = tempfile::tempdir().unwrap();
    for groups in [
        fx.groups_with_orphans(Orphans::Ignore),
        Groups::per_mask(&fx.masks),
        fx.blend_groups(Orphans::Ignore),
        fx.blend_groups(Orphans::Singleton),
    ] {
        let scene = fx.scene();
        let whole = fuse(&scene, &groups, &FuseOptions::default()).unwrap();
        let expected = bytes(&whole, dir.path(), "whole.safetensors");
        let mut parts = Vec::new();
        for (i, range) in [0..1, 1..3, 3..4].into_iter().enumerate() {
            let p = accumulate(&scene, &groups, 10, range, &mut |_| {}).unwrap();
            let path = dir.path().join(format!("part{i}.safetensors"));
            p.write(&path).unwrap();
            let back = PartialSums::read(&path).unwrap();
            assert_eq!(back.weights(), p.weights());
            assert_eq!(back.mask_mass(), p.mask_mass());
            assert_eq!(back.views(), p.views());
            assert_eq!(back.groups(), p.groups());
            assert_eq!(back.mask_features(), p.mask_features());
            assert_eq!(back.counts(), p.counts());
            assert_eq!((back.k(), back.num_views()), (10, 4));
            parts.push(back);
        }
        parts.reverse();
        let merged = merge(&parts, &[]).unwrap();
        assert!(merged.is_complete());
        let precision = Precision::of(&fx.masks.features);
        let got = bytes(
            &finish(&merged, precision),
            dir.path(),
            "merged.safetensors",
        );
        assert_eq!(got, expected, "{:?}", groups.grouping);
        assert_eq!(merged.counts(), whole_counts(&scene, &groups));
    }
}

/// The job-level finish of a sharded run (what `profuse fuse-shard` + `profuse run
/// --fuse-partials` and the Ray driver do): the bytes of an unsharded job, and shards of
/// other inputs are refused, naming the field that differs.
#[test]
fn job_shards_finish_to_the_unsharded_bytes_and_foreign_shards_are_refused() {
    use profuse_fuse::job::{run, run_merged, Job, Params};
    let fx = tiny(23, 6000);
    let dir = tempfile::tempdir().unwrap();
    let file = |n: &str| dir.path().join(n);
    fx.proposals(1)
        .write(file("proposals.safetensors"))
        .unwrap();
    fx.proposals_without_first()
        .write(file("other_proposals.safetensors"))
        .unwrap();
    let base = Job::new(
        &fx.path.join("gt/gaussians.safetensors"),
        &fx.path.join("cameras.safetensors"),
        &fx.path.join("masks.safetensors"),
    );
    let params = Params::default();
    let job = base.clone().with_proposals(&file("proposals.safetensors"));
    run(
        &job.clone().with_out(&file("whole.safetensors")),
        &params,
        &mut |_| {},
    )
    .unwrap();
    let shard = |job: &Job, range: std::ops::Range<usize>, name: &str| {
        let mut j = job.clone();
        j.views = Some(range);
        j.partial_out = Some(file(name));
        run(&j, &params, &mut |_| {}).unwrap();
        file(name)
    };
    let shards = vec![
        shard(&job, 0..3, "a.safetensors"),
        shard(&job, 3..4, "b.safetensors"),
    ];
    let merged = run_merged(
        &job.clone().with_out(&file("merged.safetensors")),
        &params,
        &shards,
    )
    .unwrap();
    assert_eq!(
        std::fs::read(file("merged.safetensors")).unwrap(),
        std::fs::read(file("whole.safetensors")).unwrap()
    );
    assert_eq!(merged.report.views, [0, 4]);
    assert!(merged.partial.is_complete());

    // A shard made with other proposals (e.g. before warp-graph ran again).
    let other = job
        .clone()
        .with_proposals(&file("other_proposals.safetensors"));
    let foreign = vec![shards[0].clone(), shard(&other, 3..4, "c.safetensors")];
    let err = run_merged(
        &job.clone().with_out(&file("x.safetensors")),
        &params,
        &foreign,
    )
    .unwrap_err();
    assert!(matches!(err, FuseError::PartialMismatch { .. }), "{err}");
    let all_other = vec![shard(&other, 0..3, "d.safetensors"), file("c.safetensors")];
    let err = run_merged(
        &job.clone().with_out(&file("x.safetensors")),
        &params,
        &all_other,
    )
    .unwrap_err();
    match &err {
        FuseError::ShardOfOtherInputs { field, shards, .. } => {
            assert!(
                ["num_groups", "mask_group", "mask_proposal"].contains(field),
                "{err}"
            );
            assert!(shards.contains("d.safetensors"), "{err}");
        }
        e => panic!("expected ShardOfOtherInputs, got {e}"),
    }
    // Another K, and a shard set missing a view.
    let k20 = Params { k: 20, ..params };
    let err = run_merged(&job.clone().with_out(&file("x.safetensors")), &k20, &shards).unwrap_err();
    assert!(
        matches!(err, FuseError::ShardOfOtherInputs { field: "k", .. }),
        "{err}"
    );
    let err = run_merged(
        &job.clone().with_out(&file("x.safetensors")),
        &params,
        &shards[..1],
    )
    .unwrap_err();
    assert!(matches!(err, FuseError::MissingViews { .. }), "{err}");
    assert!(
        !file("x.safetensors").exists(),
        "a refused finish writes nothing"
    );
}

fn whole_counts(scene: &Scene<'_>, groups: &Groups) -> profuse_fuse::HitCounts {
    accumulate(scene, groups, 10, 0..4, &mut |_| {})
        .unwrap()
        .counts()
}

#[test]
fn thread_count_does_not_change_the_bytes() {
    let fx = tiny(19, 9000);
    let dir = tempfile::tempdir().unwrap();
    for groups in [
        fx.groups(1, Orphans::Singleton),
        fx.blend_groups(Orphans::Ignore),
    ] {
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let reg = pool.install(|| fuse(&fx.scene(), &groups, &f32_opts()).unwrap());
            bytes(&reg, dir.path(), &format!("t{threads}.safetensors"))
        };
        let one = run(1);
        assert_eq!(one, run(4), "{:?}", groups.grouping);
        assert_eq!(one, run(3), "{:?}", groups.grouping);
    }
}

/// Views without a mask pixel are skipped but reported, in order, while the views around
/// them are merged as usual (registration overlaps one view's merge with the next view's
/// render): the sums equal those of the rendered views' shards merged.
#[test]
fn views_without_masks_are_reported_in_order_and_change_nothing() {
    let fx = tiny(29, 9000);
    let Labels::U16(labels) = &fx.masks.labels else {
        panic!("synth writes U16 labels")
    };
    let plane = fx.masks.width * fx.masks.height;
    let blanked: Vec<u16> = labels
        .iter()
        .enumerate()
        .map(|(i, l)| {
            if matches!(i / plane, 1 | 3) {
                u16::MAX
            } else {
                *l
            }
        })
        .collect();
    let masks = Masks {
        labels: Labels::U16(blanked.into()),
        ..fx.masks.clone()
    };
    let groups = Groups::per_mask(&masks);
    let scene = Scene::new(&fx.gaussians, &fx.cameras, &masks);
    let mut reports = Vec::new();
    let whole = accumulate(&scene, &groups, 10, 0..4, &mut |r| reports.push(*r)).unwrap();
    let seen: Vec<(usize, bool)> = reports.iter().map(|r| (r.view, r.rendered)).collect();
    assert_eq!(seen, [(0, true), (1, false), (2, true), (3, false)]);
    assert_eq!(reports[1].counts, Default::default());
    assert!(reports[0].counts.hits > 0 && reports[2].counts.hits > 0);
    assert!(reports[0].nnz > 0 && reports[0].nnz <= reports[2].nnz);
    assert_eq!(reports[2].nnz, reports[3].nnz);
    let parts: Vec<PartialSums> = [0..1, 2..3]
        .into_iter()
        .map(|r| accumulate(&scene, &groups, 10, r, &mut |_| {}).unwrap())
        .collect();
    let merged = merge(&parts, &[]).unwrap();
    assert_eq!(merged.weights(), whole.weights());
    assert_eq!(merged.mask_mass(), whole.mask_mass());
    assert_eq!(merged.counts(), whole.counts());
    // An odd and an even number of rendered views end the pass.
    for range in [0..3, 0..2, 2..4] {
        let mut n = 0;
        accumulate(&scene, &groups, 10, range.clone(), &mut |_| n += 1).unwrap();
        assert_eq!(n, range.len());
    }
}

/// Memory does not grow with the number of views: rendering every view a second time
/// (cameras and masks duplicated, the copies in the same proposals) adds no W entry and no
/// accumulator byte, and the per-view buffers stay one view's.
#[test]
fn accumulator_size_is_independent_of_the_number_of_views() {
    let fx = tiny(23, 9000);
    let (c, m) = (&fx.cameras, &fx.masks);
    let v = c.len();
    let twice = |names: &[String]| {
        names
            .iter()
            .chain(names)
            .enumerate()
            .map(|(i, n)| if i < v { n.clone() } else { format!("{n}#2") })
            .collect::<Vec<_>>()
    };
    let cameras = Cameras {
        image_names: twice(&c.image_names),
        image_size: [&c.image_size[..], &c.image_size[..]].concat().into(),
        intrinsics: [&c.intrinsics[..], &c.intrinsics[..]].concat().into(),
        world_to_camera: [&c.world_to_camera[..], &c.world_to_camera[..]]
            .concat()
            .into(),
        ..c.clone()
    };
    let Labels::U16(labels) = &m.labels else {
        panic!("synth writes U16 labels")
    };
    let total = m.num_masks() as u32;
    let offsets: Vec<u32> = m
        .mask_offsets
        .iter()
        .copied()
        .chain(m.mask_offsets[1..].iter().map(|o| o + total))
        .collect();
    let Floats::F16(f) = &m.features else {
        panic!("synth writes F16 features")
    };
    let masks = Masks {
        view_names: twice(&m.view_names),
        labels: Labels::U16([&labels[..], &labels[..]].concat().into()),
        mask_offsets: offsets.into(),
        features: Floats::F16([&f[..], &f[..]].concat().into()),
        ..m.clone()
    };
    let p = fx.proposals(1);
    let proposals = Proposals {
        mask_proposal: [&p.mask_proposal[..], &p.mask_proposal[..]].concat().into(),
        proposal_size: p
            .proposal_size
            .iter()
            .map(|s| 2 * s)
            .collect::<Vec<_>>()
            .into(),
        proposal_views: p
            .proposal_views
            .iter()
            .map(|s| 2 * s)
            .collect::<Vec<_>>()
            .into(),
        ..p.clone()
    };
    let groups = share_groups(&masks, &proposals, Orphans::Ignore);
    let scene = Scene::new(&fx.gaussians, &cameras, &masks);
    let mut reports = Vec::new();
    let doubled = accumulate(&scene, &groups, 10, 0..2 * v, &mut |r| reports.push(*r)).unwrap();
    let views: Vec<usize> = reports.iter().map(|r| r.view).collect();
    assert_eq!(
        views,
        (0..2 * v).collect::<Vec<_>>(),
        "one report per view, in order"
    );
    let first = &reports[v - 1];
    let last = &reports[2 * v - 1];
    assert_eq!(first.nnz, last.nnz);
    assert_eq!(first.accumulator_bytes, last.accumulator_bytes);
    // The per-view buffers (two views' tile records, one view's sorted records; no
    // image-sized list buffer) are sized by the largest views so far, which the repeated
    // views do not grow.
    assert!(reports.iter().all(|r| r.view_buffer_bytes > 0));
    assert_eq!(first.view_buffer_bytes, last.view_buffer_bytes);
    let scratch = last.view_buffer_bytes;
    let hits = reports.iter().map(|r| r.counts.hits).max().unwrap() as usize;
    assert!(
        scratch <= 4 * 24 * hits + 16 * masks.num_masks() + (1 << 16),
        "{scratch}"
    );
    // O(nnz): 4 bytes per Gaussian, at most 2 x 24 per pair (vector growth), 16 per mask,
    // and 24 per block of 4096 Gaussians.
    let bound = 4 * fx.gaussians.len() + 48 * last.nnz + 16 * masks.num_masks() + 4096;
    assert!(
        last.accumulator_bytes <= bound,
        "{} > {bound}",
        last.accumulator_bytes
    );

    // Every sum exactly doubled; the descriptors are the same.
    let single = accumulate(
        &fx.scene(),
        &fx.groups(1, Orphans::Ignore),
        10,
        0..v,
        &mut |_| {},
    )
    .unwrap();
    assert_eq!(single.weights().offsets, doubled.weights().offsets);
    assert_eq!(single.weights().groups, doubled.weights().groups);
    assert!(single
        .weights()
        .sums
        .iter()
        .zip(&doubled.weights().sums)
        .all(|(a, b)| 2 * a == *b));
    let a = finish(&single, Precision::F32).features;
    let b = finish(&doubled, Precision::F32).features;
    assert_eq!(a.valid, b.valid);
    let (fa, fb) = (a.features.to_f32_vec(), b.features.to_f32_vec());
    assert!(fa.iter().zip(&fb).all(|(x, y)| (x - y).abs() < 1e-6));
    let (sa, sb) = (a.weight_sum.unwrap(), b.weight_sum.unwrap());
    assert!(sa.iter().zip(sb.iter()).all(|(x, y)| 2.0 * x == *y));
}

#[test]
fn weights_are_quantised_exactly() {
    let mut w = 1.0f32;
    while w > 1e-9 {
        for x in [w, w * 0.7317, w * 0.999_999_9] {
            assert_eq!(dequantise(u128::from(quantise(x))), f64::from(x), "{x}");
        }
        w *= 0.5;
    }
    assert_eq!(quantise(0.0), 0);
    assert_eq!(quantise(-1.0), 0);
    assert_eq!(quantise(f32::NAN), 0);
}

// ---------------------------------------------------------------------------------------
// Errors.

/// Copies a safetensors file with one tensor's bytes changed.
fn rewrite_tensor(from: &Path, to: &Path, name: &str, change: impl Fn(&[u8]) -> Vec<u8>) {
    let c = Container::open(from).unwrap();
    let mut w = FileWriter::new(Kind::Features);
    for (k, v) in c.metadata() {
        w.meta(k, v.clone());
    }
    for (t, info) in c.tensors() {
        let raw = c.raw(t).unwrap();
        let bytes = if t == name { change(raw) } else { raw.to_vec() };
        w.raw_tensor(t, info.dtype, &info.shape, bytes);
    }
    w.commit(to).unwrap();
}

#[test]
fn mismatched_inputs_are_typed_errors_naming_the_inputs() {
    let fx = tiny(29, 500);
    let groups = fx.groups(1, Orphans::Ignore);
    // Masks of other views.
    let mut renamed = fx.masks.clone();
    renamed.view_names[2] = "elsewhere.png".into();
    let names = profuse_fuse::Names {
        masks: "m.safetensors".into(),
        cameras: "c.safetensors".into(),
        ..Default::default()
    };
    let scene = Scene::new(&fx.gaussians, &fx.cameras, &renamed).named(names);
    let err = fuse(&scene, &groups, &FuseOptions::default()).unwrap_err();
    assert!(matches!(err, FuseError::ViewMismatch { .. }));
    let text = err.to_string();
    assert!(
        text.contains("m.safetensors") && text.contains("c.safetensors") && text.contains("view 2"),
        "{text}"
    );
    // Proposals of another masks file.
    let mut p = fx.proposals(1);
    p.mask_proposal = p.mask_proposal[1..].to_vec().into();
    let err = Groups::from_proposals(
        &fx.masks,
        &p,
        Orphans::Ignore,
        MemberWeight::Share,
        "p.safetensors",
    )
    .unwrap_err();
    assert!(err.to_string().contains("p.safetensors"), "{err}");
    // A grouping built in memory that points past its groups.
    let mut broken = groups.clone();
    broken.mask_group[1] = broken.num_groups as u32;
    let err = fuse(&fx.scene(), &broken, &FuseOptions::default()).unwrap_err();
    assert!(matches!(err, FuseError::BadGrouping { .. }), "{err}");
    assert!(err.to_string().contains("mask 1"), "{err}");
    // Views out of range, K out of range.
    let scene = fx.scene();
    let err = accumulate(&scene, &groups, 10, 3..9, &mut |_| {}).unwrap_err();
    assert!(
        matches!(
            err,
            FuseError::ViewRange {
                end: 9,
                views: 4,
                ..
            }
        ),
        "{err}"
    );
    let err = accumulate(&scene, &groups, 0, 0..4, &mut |_| {}).unwrap_err();
    assert!(matches!(err, FuseError::Render { .. }), "{err}");
}

#[test]
fn merge_rejects_overlaps_mismatches_and_corrupt_files() {
    let fx = tiny(31, 500);
    let groups = fx.groups(1, Orphans::Ignore);
    let scene = fx.scene();
    let a = accumulate(&scene, &groups, 10, 0..2, &mut |_| {}).unwrap();
    let b = accumulate(&scene, &groups, 10, 1..4, &mut |_| {}).unwrap();
    let names = ["a.st".to_string(), "b.st".to_string()];
    let err = merge(&[a.clone(), b], &names).unwrap_err();
    assert!(
        matches!(err, FuseError::ViewOverlap { view: 1, .. }),
        "{err}"
    );
    assert!(err.to_string().contains("a.st") && err.to_string().contains("b.st"));

    let c = accumulate(&scene, &groups, 8, 2..4, &mut |_| {}).unwrap();
    let err = merge(&[a.clone(), c], &names).unwrap_err();
    assert_partial_mismatch(&err, "k");
    let other = accumulate(
        &scene,
        &fx.groups(1, Orphans::Singleton),
        10,
        2..4,
        &mut |_| {},
    )
    .unwrap();
    let err = merge(&[a.clone(), other], &names).unwrap_err();
    assert_partial_mismatch(&err, "orphans");

    // Member shares travel in the partial files: shards merge to the single run's
    // descriptors, a file keeps them, and shards with other shares (or none) are refused.
    let mut shared = groups.clone();
    shared.mask_share = (0..fx.masks.num_masks())
        .map(|m| 0.25 + 0.25 * (m % 4) as f32)
        .collect();
    let first = accumulate(&scene, &shared, 10, 0..2, &mut |_| {}).unwrap();
    let second = accumulate(&scene, &shared, 10, 2..4, &mut |_| {}).unwrap();
    let whole = accumulate(&scene, &shared, 10, 0..4, &mut |_| {}).unwrap();
    let merged = merge(&[first.clone(), second.clone()], &names).unwrap();
    assert_eq!(group_descriptors(&merged), group_descriptors(&whole));
    let without = accumulate(&scene, &groups, 10, 0..4, &mut |_| {}).unwrap();
    assert_ne!(group_descriptors(&whole), group_descriptors(&without));
    let dir = tempfile::tempdir().unwrap();
    first.write(dir.path().join("first.st")).unwrap();
    let back = PartialSums::read(dir.path().join("first.st")).unwrap();
    assert_eq!(back.groups(), first.groups());
    let err = merge(&[a.clone(), second], &names).unwrap_err();
    assert_partial_mismatch(&err, "mask_share");

    let half = merge(std::slice::from_ref(&a), &[]).unwrap();
    assert!(!half.is_complete());
    assert_eq!(half.missing_views(), "2..4");
    assert!(matches!(merge(&[], &[]), Err(FuseError::NothingToMerge)));

    // A partial file whose rows are not sorted is rejected, naming file and tensor.
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good.safetensors");
    a.write(&good).unwrap();
    let path = dir.path().join("bad.safetensors");
    rewrite_tensor(&good, &path, "w_groups", |bytes| {
        let groups: Vec<u32> = bytemuck::pod_collect_to_vec(bytes);
        let offsets = a.weights().offsets.clone();
        let row = (0..a.weights().rows())
            .find(|g| offsets[g + 1] - offsets[*g] >= 2)
            .expect("a Gaussian with two groups");
        let mut groups = groups;
        groups.swap(offsets[row] as usize, offsets[row] as usize + 1);
        bytemuck::cast_slice(&groups).to_vec()
    });
    let err = PartialSums::read(&path).unwrap_err();
    let FuseError::Format(e) = &err else {
        panic!("{err}")
    };
    assert_eq!((e.code(), e.field()), ("out_of_range", Some("w_groups")));
    assert!(err.to_string().contains("bad.safetensors"));
    // Another kind of file.
    let err = PartialSums::read(fx.path.join("masks.safetensors")).unwrap_err();
    assert!(err.to_string().contains("profuse.fuse_partial"), "{err}");
}

/// Blend shards do not merge with shards of another grouping or other proposals, and a
/// blend partial file whose proposals or groups were tampered with is rejected, naming the
/// file and the tensor.
#[test]
fn blend_partial_files_are_checked() {
    let fx = tiny(31, 500);
    let scene = fx.scene();
    let blend = fx.blend_groups(Orphans::Ignore);
    let a = accumulate(&scene, &blend, 10, 0..2, &mut |_| {}).unwrap();
    let names = ["a.st".to_string(), "b.st".to_string()];
    let paper = accumulate(
        &scene,
        &fx.groups_with_orphans(Orphans::Ignore),
        10,
        2..4,
        &mut |_| {},
    )
    .unwrap();
    let err = merge(&[a.clone(), paper], &names).unwrap_err();
    assert_partial_mismatch(&err, "grouping");
    let masks = accumulate(&scene, &Groups::per_mask(&fx.masks), 10, 2..4, &mut |_| {}).unwrap();
    let err = merge(&[a.clone(), masks], &names).unwrap_err();
    assert_partial_mismatch(&err, "grouping");
    // The same groups (masks), but a mask in another proposal.
    let mut other = blend.clone();
    let moved = other
        .mask_proposal
        .iter()
        .position(|p| *p != NO_GROUP)
        .unwrap();
    other.mask_proposal[moved] = if other.mask_proposal[moved] == 0 {
        1
    } else {
        0
    };
    let b = accumulate(&scene, &other, 10, 2..4, &mut |_| {}).unwrap();
    let err = merge(&[a.clone(), b], &names).unwrap_err();
    assert_partial_mismatch(&err, "mask_proposal");
    let b = accumulate(
        &scene,
        &fx.blend_groups(Orphans::Singleton),
        10,
        2..4,
        &mut |_| {},
    )
    .unwrap();
    assert!(merge(&[a.clone(), b], &names).is_err());

    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good.safetensors");
    a.write(&good).unwrap();
    assert_eq!(PartialSums::read(&good).unwrap().groups(), a.groups());
    let orphan = blend
        .mask_proposal
        .iter()
        .position(|p| *p == NO_GROUP)
        .expect("an orphan");
    // An ignored orphan given a proposal, but still in no group.
    let path = dir.path().join("proposal.safetensors");
    rewrite_tensor(&good, &path, "mask_proposal", |bytes| {
        let mut ids: Vec<u32> = bytemuck::pod_collect_to_vec(bytes);
        ids[orphan] = 0;
        bytemuck::cast_slice(&ids).to_vec()
    });
    let err = PartialSums::read(&path).unwrap_err();
    let FuseError::Format(e) = &err else {
        panic!("{err}")
    };
    assert_eq!((e.code(), e.field()), ("invalid", Some("mask_group")));
    assert!(err.to_string().contains("proposal.safetensors"), "{err}");
    // The proposals tensor missing.
    let path = dir.path().join("missing.safetensors");
    {
        let c = Container::open(&good).unwrap();
        let mut w = FileWriter::new(Kind::Features);
        for (k, v) in c.metadata() {
            w.meta(k, v.clone());
        }
        for (t, info) in c.tensors() {
            if t != "mask_proposal" {
                w.raw_tensor(t, info.dtype, &info.shape, c.raw(t).unwrap().to_vec());
            }
        }
        w.commit(&path).unwrap();
    }
    let err = PartialSums::read(&path).unwrap_err();
    assert!(
        err.to_string().contains("missing.safetensors")
            && err.to_string().contains("mask_proposal"),
        "{err}"
    );
    // A proposals tensor in a file of another grouping.
    let paper_file = dir.path().join("paper.safetensors");
    accumulate(
        &scene,
        &fx.groups(1, Orphans::Ignore),
        10,
        0..2,
        &mut |_| {},
    )
    .unwrap()
    .write(&paper_file)
    .unwrap();
    let path = dir.path().join("extra.safetensors");
    {
        let c = Container::open(&paper_file).unwrap();
        let mut w = FileWriter::new(Kind::Features);
        for (k, v) in c.metadata() {
            w.meta(k, v.clone());
        }
        for (t, info) in c.tensors() {
            w.raw_tensor(t, info.dtype, &info.shape, c.raw(t).unwrap().to_vec());
        }
        let m = fx.masks.num_masks();
        w.raw_tensor(
            "mask_proposal",
            profuse_formats::Dtype::U32,
            &[m],
            vec![0u8; 4 * m],
        );
        w.commit(&path).unwrap();
    }
    let err = PartialSums::read(&path).unwrap_err();
    let FuseError::Format(e) = &err else {
        panic!("{err}")
    };
    assert_eq!((e.code(), e.field()), ("invalid", Some("mask_proposal")));
    // A grouping built in memory whose groups do not follow its proposals.
    let mut broken = blend.clone();
    broken.mask_group[orphan] = orphan as u32;
    let err = accumulate(&scene, &broken, 10, 0..4, &mut |_| {}).unwrap_err();
    assert!(matches!(err, FuseError::BadGrouping { .. }), "{err}");
    assert!(err.to_string().contains(&format!("mask {orphan}")), "{err}");
}

// ---------------------------------------------------------------------------------------
// Semantic index (issue 24).

/// Brute force over one Gaussian's W row mapped to table rows: the row with the most
/// weight (ties to the lower row) and its share, from `WeightMatrix::get` per group.
fn brute_dominant(p: &PartialSums, g: usize, row_of: &dyn Fn(u32) -> u32) -> Option<(u32, f64)> {
    let mut per_row: std::collections::BTreeMap<u32, f64> = Default::default();
    for group in 0..p.groups().num_groups as u32 {
        let w = p.weights().get(g, group);
        if w > 0.0 {
            *per_row.entry(row_of(group)).or_default() += w;
        }
    }
    let total: f64 = per_row.values().sum();
    let (row, w) = per_row
        .iter()
        .fold(None::<(u32, f64)>, |best, (r, w)| match best {
            Some((_, b)) if b >= *w => best,
            _ => Some((*r, *w)),
        })?;
    Some((row, w / total))
}

#[test]
fn semantic_index_matches_the_brute_force_dominant_proposal() {
    let fx = tiny(3, 9000);
    for orphans in [Orphans::Ignore, Orphans::Singleton] {
        let groups = fx.groups_with_orphans(orphans);
        let partial = accumulate(&fx.scene(), &groups, 10, 0..4, &mut |_| {}).unwrap();
        let reg = finish(&partial, Precision::F32);
        let index = profuse_fuse::semantic_index(&partial, Precision::F32, 0.5);
        index.validate("index").unwrap();
        assert_eq!(index.min_share, 128);
        // min_share 0: the same rows and index without the share (2 bytes a Gaussian),
        // every Gaussian with a row dominant.
        let compact = profuse_fuse::semantic_index(&partial, Precision::F32, 0.0);
        compact.validate("compact").unwrap();
        assert!(compact.share.is_none() && index.share.is_some());
        assert_eq!(
            (&compact.index, &compact.descriptors),
            (&index.index, &index.descriptors)
        );
        let with_row = (0..index.num_gaussians()).filter(|&g| index.proposal(g).is_some());
        assert!(with_row.clone().all(|g| compact.is_dominant(g)));
        assert!(with_row.clone().any(|g| !index.is_dominant(g)));
        assert_eq!(index.num_proposals(), groups.num_groups);
        // The table is the group descriptors of the registration.
        let table: Vec<f32> = profuse_fuse::group_descriptors(&partial)
            .iter()
            .map(|x| *x as f32)
            .collect();
        assert_eq!(index.descriptors.to_f32_vec(), table);
        let d = index.dim;
        let (mut mixed, mut single) = (0, 0);
        for g in 0..index.num_gaussians() {
            let want = brute_dominant(&partial, g, &|group| group);
            assert_eq!(index.proposal(g), want.map(|w| w.0), "g {g}");
            let share = want.map_or(0, |w| profuse_formats::quantise_share(w.1));
            assert!(
                index.share_of(g).abs_diff(share) <= 1,
                "g {g}: share {} vs {share}",
                index.share_of(g)
            );
            let (groups_of_g, _) = partial.weights().row(g);
            if groups_of_g.len() == 1 && reg.features.valid[g] == 1 {
                // All its weight in one proposal: its descriptor is that table row.
                single += 1;
                assert_eq!(index.share_of(g), 255);
                let r = index.proposal(g).unwrap() as usize;
                let f = reg.features.features.to_f32_vec();
                assert_eq!(f[g * d..][..d], table[r * d..][..d], "g {g}");
            } else if groups_of_g.len() > 1 {
                mixed += 1;
            }
        }
        assert!(
            single > 1000 && mixed > 100,
            "{single} single, {mixed} mixed"
        );
        let counts = profuse_formats::FileKind::counts(&index);
        assert_eq!(
            counts["indexed"] as usize,
            (0..reg.features.len())
                .filter(|&g| !partial.weights().row(g).0.is_empty())
                .count()
        );
    }
}

#[test]
fn semantic_index_under_blend_indexes_the_registered_rows() {
    let fx = tiny(3, 6000);
    let groups = fx.blend_groups(Orphans::Singleton);
    let partial = accumulate(&fx.scene(), &groups, 10, 0..4, &mut |_| {}).unwrap();
    let reg = finish(&partial, Precision::F32);
    let index = profuse_fuse::semantic_index(&partial, Precision::F32, 0.5);
    index.validate("index").unwrap();
    // Each mask's registered descriptor is a row of the table (masks that keep their
    // proposal's descriptor share its row).
    let d = index.dim;
    let table = index.descriptors.to_f32_vec();
    let rows: Vec<&[f32]> = table.chunks_exact(d).collect();
    let mask_rows: Vec<Option<u32>> = registered_mask_descriptors(&partial)
        .iter()
        .map(|m| {
            m.as_ref()
                .map(|f| rows.iter().position(|r| *r == f.as_slice()).unwrap() as u32)
        })
        .collect();
    let group_row = |group: u32| mask_rows[group as usize].unwrap();
    for g in 0..index.num_gaussians() {
        let want = brute_dominant(&partial, g, &group_row);
        assert_eq!(index.proposal(g), want.map(|w| w.0), "g {g}");
    }
    assert!(reg.summary.valid > 1000);
}

#[test]
fn job_writes_the_semantic_index_and_refuses_a_bad_min_share() {
    use profuse_fuse::job::{run, Job, Params};
    let fx = tiny(23, 3000);
    let dir = tempfile::tempdir().unwrap();
    let file = |n: &str| dir.path().join(n);
    fx.proposals(1)
        .write(file("proposals.safetensors"))
        .unwrap();
    let mut job = Job::new(
        &fx.path.join("gt/gaussians.safetensors"),
        &fx.path.join("cameras.safetensors"),
        &fx.path.join("masks.safetensors"),
    )
    .with_proposals(&file("proposals.safetensors"))
    .with_out(&file("features.safetensors"));
    job.semantic_index = Some(file("index.safetensors"));
    let bad = Params {
        min_share: 1.5,
        ..Params::default()
    };
    let err = run(&job, &bad, &mut |_| {}).unwrap_err();
    assert!(matches!(err, FuseError::MinShare(_)), "{err}");
    assert!(!file("features.safetensors").exists() && !file("index.safetensors").exists());
    let report = run(&job, &Params::default(), &mut |_| {}).unwrap().report;
    let index = profuse_formats::SemanticIndex::read(file("index.safetensors")).unwrap();
    let features = profuse_formats::Features::read(file("features.safetensors")).unwrap();
    assert_eq!(index.num_gaussians(), features.len());
    assert_eq!(
        report.dominant,
        Some(profuse_formats::FileKind::counts(&index)["dominant"] as usize)
    );
    // Same precision as the features (the masks' F16 here), and a Gaussian with weight
    // has a proposal exactly when it has a descriptor.
    assert_eq!(index.descriptors.dtype(), features.features.dtype());
    for g in 0..features.len() {
        assert_eq!(index.proposal(g).is_some(), features.valid[g] == 1, "g {g}");
    }
}

/// Merged masks (synth `p_merge` 0.5: a mask spanning two objects, put in its dominant
/// object's proposal) with the share a perfect consensus would write (their purity): under
/// the paper's ω a merged member paints its proposal's descriptor over the part of the
/// neighbour it covers; with pixels weighing ω · s^4 (the default exponent) more Gaussians
/// keep their own class (nearest class centroid of the clean masks' features).
#[test]
fn merged_members_paint_fewer_neighbours_when_pixels_weigh_their_share() {
    let fx = tiny_with(14, 3000, |c| {
        c.faults.p_merge = 0.5;
        c.faults.p_wrong_class = 0.0;
    });
    let d = fx.masks.dim;
    let entries = fx.mask_objects();
    let class_of_mask = fx.mask_classes();
    let purity: Vec<f32> = entries
        .iter()
        .map(|e| (e["purity"].as_f64().unwrap_or(1.0) as f32).clamp(0.01, 1.0))
        .collect();
    let merged = purity.iter().filter(|p| **p < 0.9).count();
    assert!(merged >= 5, "{merged} merged masks");
    let proposals = Proposals {
        mask_share: Some(purity.clone().into()),
        ..fx.proposals(1)
    };
    // Class centroids of the pure masks' features.
    let mut centroids: std::collections::BTreeMap<i64, Vec<f64>> = Default::default();
    for (m, c) in class_of_mask.iter().enumerate() {
        if let (Some(c), true) = (c, purity[m] >= 0.95) {
            let row = centroids.entry(*c).or_insert_with(|| vec![0.0; d]);
            for (j, x) in row.iter_mut().enumerate() {
                *x += f64::from(fx.masks.features.get(m * d + j));
            }
        }
    }
    let classes = fx.gaussians.class_ids.as_ref().unwrap();
    let wrong = |power: f64| {
        let groups = share_groups(&fx.masks, &proposals, Orphans::Ignore)
            .with_pixel_shares(&proposals, power)
            .unwrap();
        let f = fuse(&fx.scene(), &groups, &f32_opts()).unwrap().features;
        let mut wrong = 0;
        for g in 0..fx.gaussians.len() {
            let class = i64::from(classes[g]);
            if f.valid[g] == 0 || !centroids.contains_key(&class) {
                continue;
            }
            let row: Vec<f64> = (0..d)
                .map(|j| f64::from(f.features.get(g * d + j)))
                .collect();
            let best = centroids
                .iter()
                .max_by(|x, y| {
                    let dot = |c: &[f64]| c.iter().zip(&row).map(|(a, b)| a * b).sum::<f64>();
                    dot(x.1).total_cmp(&dot(y.1))
                })
                .map(|(c, _)| *c);
            wrong += usize::from(best != Some(class));
        }
        wrong
    };
    let (paper, weighed) = (wrong(0.0), wrong(profuse_fuse::DEFAULT_PIXEL_SHARE_POWER));
    eprintln!(
        "Gaussians off their class: paper {paper}, weighed {weighed} ({merged} merged masks)"
    );
    assert!(weighed * 4 < paper * 3, "{paper} {weighed}");
}
