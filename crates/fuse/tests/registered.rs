//! `registered_mask_descriptors`: what each mask's pixels register, checked against the
//! groups and the group descriptors, and against a Gaussian fed by one group only.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use profuse_formats::{Cameras, FileKind, Gaussians, Masks, Proposals};
use profuse_fuse::{
    accumulate, group_descriptors, registered_mask_descriptors, Groups, Orphans, Scene, NO_GROUP,
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
    let groups = Groups::from_proposals(&masks, &proposals, Orphans::Ignore, "p").unwrap();
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

/// `pooled_descriptor` of a proposal's members, rendering only their views, equals the
/// proposal's row of a full registration over every view, bit for bit in f32; a member
/// set without mass is `None`, and an id beyond the masks is an error.
#[test]
fn pooled_descriptor_of_a_proposal_equals_its_row_of_the_full_registration() {
    let TinyScene {
        gaussians,
        cameras,
        masks,
        proposals,
        ..
    } = tiny_scene(3, 3000, 1);
    let scene = Scene::new(&gaussians, &cameras, &masks);
    let d = masks.dim;
    let groups = Groups::from_proposals(&masks, &proposals, Orphans::Ignore, "p").unwrap();
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
        let got = profuse_fuse::pooled_descriptor(&scene, &members, 10).unwrap();
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
        profuse_fuse::pooled_descriptor(&scene, &[], 10).unwrap(),
        None
    );
    let m = masks.num_masks() as u32;
    assert!(matches!(
        profuse_fuse::pooled_descriptor(&scene, &[m], 10),
        Err(profuse_fuse::FuseError::BadGrouping { .. })
    ));
}
