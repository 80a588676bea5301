//! `registered_mask_descriptors`: what each mask's pixels register, checked against the
//! groups and the group descriptors, and against a Gaussian fed by one group only.

use profuse_formats::{Cameras, FileKind, Gaussians, Masks, Proposals};
use profuse_fuse::{
    accumulate, group_descriptors, registered_mask_descriptors, Groups, MemberWeight, Orphans,
    Scene, NO_GROUP,
};

/// A synth `tiny` scene (seed, Gaussian count) and its ground-truth proposals (objects
/// with at least `min_members` masks); the directory lives as long as the scene.
struct TinyScene {
    _dir: tempfile::TempDir,
    gaussians: Gaussians,
    cameras: Cameras,
    masks: Masks,
    proposals: Proposals,
}

fn tiny_scene(seed: u64, gaussians: usize, min_members: usize) -> TinyScene {
    let dir = tempfile::tempdir().unwrap();
    let mut config = synth::Config::preset(synth::Preset::Tiny, seed);
    config.gaussians = gaussians;
    config.write_matches = false;
    synth::generate(&config, dir.path()).unwrap();
    let gaussians = Gaussians::read(dir.path().join("gt/gaussians.safetensors")).unwrap();
    let cameras = Cameras::read(dir.path().join("cameras.safetensors")).unwrap();
    let masks = Masks::read(dir.path().join("masks.safetensors")).unwrap();
    let proposals = profuse_fuse::testing::proposals_from_mask_objects(
        dir.path().join("gt/mask_objects.json"),
        &masks,
        min_members,
    )
    .unwrap();
    TinyScene {
        _dir: dir,
        gaussians,
        cameras,
        masks,
        proposals,
    }
}

#[test]
fn each_mask_gets_its_groups_descriptor_or_none() {
    let TinyScene {
        gaussians,
        cameras,
        masks,
        proposals,
        ..
    } = tiny_scene(2, 2000, 2);
    let scene = Scene::new(&gaussians, &cameras, &masks);
    let d = masks.dim;

    // Proposals (objects with a single mask are orphans and register nothing).
    let groups = Groups::from_proposals(
        &masks,
        &proposals,
        Orphans::Ignore,
        MemberWeight::Share,
        "p",
    )
    .unwrap();
    let partial = accumulate(&scene, &groups, 10, 0..cameras.len(), &mut |_| {}).unwrap();
    let desc = group_descriptors(&partial);
    let reg = registered_mask_descriptors(&partial);
    assert_eq!(reg.len(), masks.num_masks());
    let mut orphans = 0;
    for (m, r) in reg.iter().enumerate() {
        let g = groups.mask_group[m];
        if g == NO_GROUP {
            orphans += 1;
            assert!(r.is_none(), "orphan mask {m}");
            continue;
        }
        let want: Vec<f32> = desc[g as usize * d..][..d]
            .iter()
            .map(|x| *x as f32)
            .collect();
        match r {
            Some(r) => assert_eq!(r, &want, "mask {m}"),
            None => assert!(want.iter().all(|x| *x == 0.0), "mask {m}"),
        }
    }
    assert!(orphans > 0 && orphans < masks.num_masks());
    // Masks of one proposal register the same descriptor.
    for a in 0..reg.len() {
        for b in a + 1..reg.len() {
            if groups.mask_group[a] == groups.mask_group[b] && groups.mask_group[a] != NO_GROUP {
                assert_eq!(reg[a], reg[b]);
            }
        }
    }

    // Baseline: every mask registers its own (unit) feature.
    let groups = Groups::per_mask(&masks);
    let partial = accumulate(&scene, &groups, 10, 0..cameras.len(), &mut |_| {}).unwrap();
    let reg = registered_mask_descriptors(&partial);
    let mut f = vec![0f32; d];
    for (m, r) in reg.iter().enumerate() {
        masks.features.read_into(m * d, &mut f);
        let r = r.as_ref().unwrap();
        let cos: f64 = r.iter().zip(&f).map(|(a, b)| f64::from(*a * *b)).sum();
        assert!((cos - 1.0).abs() < 1e-3, "mask {m}: cosine {cos}");
    }
}

/// Shares in (0, 1] that differ from mask to mask (a stand-in for warp-graph's).
fn uneven_shares(masks: usize) -> Vec<f32> {
    (0..masks)
        .map(|m| 0.1 + 0.1 * (m * 7 % 10) as f32)
        .collect()
}

/// `pooled_descriptor` of a proposal's members, rendering only their views, equals the
/// proposal's row of a full registration over every view, bit for bit in f32, with and
/// without member shares; a member set without mass is `None`, and an id beyond the
/// masks, or shares not one per mask, is an error.
#[test]
fn pooled_descriptor_of_a_proposal_equals_its_row_of_the_full_registration() {
    let TinyScene {
        gaussians,
        cameras,
        masks,
        mut proposals,
        ..
    } = tiny_scene(3, 3000, 1);
    pooled_descriptors_match_the_registration(&gaussians, &cameras, &masks, &proposals);
    proposals.mask_share = Some(uneven_shares(masks.num_masks()).into());
    pooled_descriptors_match_the_registration(&gaussians, &cameras, &masks, &proposals);
    let scene = Scene::new(&gaussians, &cameras, &masks);
    let m = masks.num_masks() as u32;
    assert!(matches!(
        profuse_fuse::pooled_descriptor(&scene, &[0], Some(&[1.0]), 10),
        Err(profuse_fuse::FuseError::BadGrouping { .. })
    ));
    assert!(matches!(
        profuse_fuse::pooled_descriptor(&scene, &[m], None, 10),
        Err(profuse_fuse::FuseError::BadGrouping { .. })
    ));
}

fn pooled_descriptors_match_the_registration(
    gaussians: &Gaussians,
    cameras: &Cameras,
    masks: &Masks,
    proposals: &Proposals,
) {
    let scene = Scene::new(gaussians, cameras, masks);
    let d = masks.dim;
    let groups =
        Groups::from_proposals(masks, proposals, Orphans::Ignore, MemberWeight::Share, "p")
            .unwrap();
    let partial = accumulate(&scene, &groups, 10, 0..cameras.len(), &mut |_| {}).unwrap();
    let desc = group_descriptors(&partial);
    let mut checked = 0;
    for p in 0..proposals.len() as u32 {
        let members: Vec<u32> = (0..masks.num_masks() as u32)
            .filter(|&m| proposals.mask_proposal[m as usize] == p)
            .collect();
        let want: Vec<f32> = desc[p as usize * d..][..d]
            .iter()
            .map(|x| *x as f32)
            .collect();
        let shares = proposals.mask_share.as_deref();
        let got = profuse_fuse::pooled_descriptor(&scene, &members, shares, 10).unwrap();
        match got {
            Some(got) => {
                assert_eq!(got, want, "proposal {p}");
                checked += 1;
            }
            None => assert!(want.iter().all(|x| *x == 0.0), "proposal {p}"),
        }
    }
    assert!(checked >= 4, "only {checked} proposals have a descriptor");
    assert_eq!(
        profuse_fuse::pooled_descriptor(&scene, &[], None, 10).unwrap(),
        None
    );
}

/// With [`MemberWeight::Share`] a proposal's descriptor is normalise(Σ s_m μ_m f_m) over
/// its members (brute force from the masses and features); with [`MemberWeight::Mass`],
/// or a proposals file without shares, normalise(Σ μ_m f_m), the paper's.
#[test]
fn share_weighted_descriptors_equal_the_brute_force_sum() {
    let TinyScene {
        gaussians,
        cameras,
        masks,
        mut proposals,
        ..
    } = tiny_scene(4, 3000, 1);
    let scene = Scene::new(&gaussians, &cameras, &masks);
    let d = masks.dim;
    let shares = uneven_shares(masks.num_masks());
    let descriptors = |proposals: &Proposals, weight: MemberWeight| {
        let groups = Groups::from_proposals(&masks, proposals, Orphans::Ignore, weight, "p");
        let partial = accumulate(&scene, &groups.unwrap(), 10, 0..cameras.len(), &mut |_| {});
        let partial = partial.unwrap();
        (group_descriptors(&partial), partial.mask_mass().to_vec())
    };
    let (assign, count) = (proposals.mask_proposal.to_vec(), proposals.len());
    let brute = |mass: &[u128], share: &dyn Fn(usize) -> f64| -> Vec<f64> {
        let mut out = vec![0f64; count * d];
        let mut f = vec![0f32; d];
        for (m, p) in assign.iter().enumerate() {
            if *p == NO_GROUP {
                continue;
            }
            masks.features.read_into(m * d, &mut f);
            let w = profuse_fuse::dequantise(mass[m]) * share(m);
            for (o, x) in out[*p as usize * d..][..d].iter_mut().zip(&f) {
                *o += w * f64::from(*x);
            }
        }
        for row in out.chunks_exact_mut(d) {
            let norm = row.iter().map(|x| x * x).sum::<f64>().sqrt();
            row.iter_mut().for_each(|x| *x /= norm);
        }
        out
    };
    let close = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12);
    let (paper, mass) = descriptors(&proposals, MemberWeight::Share);
    assert!(close(&paper, &brute(&mass, &|_| 1.0)));
    proposals.mask_share = Some(shares.clone().into());
    let (weighted, _) = descriptors(&proposals, MemberWeight::Share);
    assert!(close(&weighted, &brute(&mass, &|m| f64::from(shares[m]))));
    assert!(!close(&weighted, &paper), "the shares changed nothing");
    let (by_mass, _) = descriptors(&proposals, MemberWeight::Mass);
    assert_eq!(by_mass, paper);
}
