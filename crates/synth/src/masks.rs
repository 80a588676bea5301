//! "SAM-like" masks from object-id maps through a seeded fault model, "CLIP-like" mask
//! features from class prototypes, and the text prompts.

use std::collections::{BTreeMap, BTreeSet};

use profuse_formats::NO_OBJECT;
use serde::Serialize;

use crate::config::{Config, FaultModel};
use crate::rng::{name_hash, tag, unit, Rng};
use profuse_formats::label_space::CANONICAL_NEGATIVES;

/// "No mask" in the per-view working label maps.
const NONE: u32 = u32::MAX;

/// The class embedding space: one seeded random unit prototype per class name.
#[derive(Debug, Clone)]
pub struct Prototypes {
    dim: usize,
    /// (class id, name, prototype) of the scene's classes, ascending id.
    classes: Vec<(u32, String, Vec<f64>)>,
}

impl Prototypes {
    /// Prototypes of the given classes (id, name) in dimension `dim`.
    pub fn new(seed: u64, dim: usize, classes: &[(u32, String)]) -> Prototypes {
        Prototypes {
            dim,
            classes: classes
                .iter()
                .map(|(id, name)| (*id, name.clone(), prototype(seed, dim, name)))
                .collect(),
        }
    }

    /// The prototype of a class id of the scene.
    pub fn of_class(&self, class_id: u32) -> Option<&[f64]> {
        self.classes
            .iter()
            .find(|c| c.0 == class_id)
            .map(|c| c.2.as_slice())
    }

    /// The scene's classes: (id, name, prototype).
    pub fn classes(&self) -> impl Iterator<Item = (u32, &str, &[f64])> {
        self.classes
            .iter()
            .map(|(i, n, p)| (*i, n.as_str(), p.as_slice()))
    }

    /// Feature dimension.
    pub fn dim(&self) -> usize {
        self.dim
    }
}

/// The seeded unit prototype of a class name in dimension `dim` (a standard normal
/// vector, normalised: independent names are nearly orthogonal for large D).
pub fn prototype(seed: u64, dim: usize, name: &str) -> Vec<f64> {
    let mut rng = Rng::new(&[seed, tag::PROTOTYPE, name_hash(name)]);
    let v: Vec<f64> = (0..dim).map(|_| rng.normal()).collect();
    normalized(v)
}

fn normalized(mut v: Vec<f64>) -> Vec<f64> {
    let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
    if n > 0.0 {
        v.iter_mut().for_each(|x| *x /= n);
    }
    v
}

/// Adds `sigma · g`, g ~ N(0, I/D), and normalises.
fn noisy(mut v: Vec<f64>, sigma: f64, rng: &mut Rng) -> Vec<f64> {
    let s = sigma / (v.len() as f64).sqrt();
    if sigma > 0.0 {
        v.iter_mut().for_each(|x| *x += s * rng.normal());
    }
    normalized(v)
}

/// One mask of a view, with its provenance.
#[derive(Debug, Clone, Serialize)]
pub(crate) struct MaskInfo {
    /// Objects whose regions formed the mask (more than one after a merge).
    pub objects: Vec<u32>,
    /// Which half of a split mask (`None` if not split).
    pub half: Option<u8>,
    /// Pixels of the final mask.
    pub pixels: u64,
    /// Ground-truth object with most pixels in the final mask.
    pub object: u32,
    /// Share of the mask's pixels on `object`.
    pub purity: f64,
    /// The class whose prototype dominates the feature.
    pub class_id: u32,
    /// The class the feature was biased toward, if any.
    pub wrong_class: Option<u32>,
    #[serde(skip)]
    pub feature: Vec<f32>,
}

/// Per-view provenance counts.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ViewProvenance {
    /// View index.
    pub view: usize,
    /// Objects with at least one pixel in the view.
    pub visible_objects: usize,
    /// Small regions dropped (missed).
    pub dropped_small: usize,
    /// Merge operations (under-segmentation).
    pub merged: usize,
    /// Masks split in two (over-segmentation).
    pub split: usize,
    /// Masks whose feature was biased toward another class.
    pub wrong_class: usize,
    /// Final masks.
    pub masks: usize,
    /// Pixels whose label was changed by boundary jitter.
    pub jittered_px: u64,
    /// Boundary pixels set to "no mask".
    pub unassigned_px: u64,
    /// Pixels without a mask in the end (dropped regions + unassigned).
    pub no_mask_px: u64,
}

/// The masks of one view.
#[derive(Debug, Clone)]
pub(crate) struct ViewMasks {
    /// View-local mask index per pixel, `u16::MAX` = none.
    pub labels: Vec<u16>,
    pub masks: Vec<MaskInfo>,
    pub provenance: ViewProvenance,
}

struct UnionFind(Vec<usize>);

impl UnionFind {
    fn find(&mut self, mut i: usize) -> usize {
        while self.0[i] != i {
            self.0[i] = self.0[self.0[i]];
            i = self.0[i];
        }
        i
    }
    fn union(&mut self, a: usize, b: usize) -> bool {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra == rb {
            return false;
        }
        // The smaller root wins, so roots do not depend on call order.
        let (lo, hi) = if ra < rb { (ra, rb) } else { (rb, ra) };
        self.0[hi] = lo;
        true
    }
}

/// One view's object-id map and the fault model, shared by the steps of [`view_masks`].
struct ViewInput<'a> {
    config: &'a Config,
    /// (seed, view) for the keyed random decisions.
    seed: u64,
    v: u64,
    ids: &'a [u32],
    width: usize,
    height: usize,
    class_of: &'a [u32],
}

impl ViewInput<'_> {
    fn faults(&self) -> &FaultModel {
        &self.config.faults
    }

    fn num_objects(&self) -> usize {
        self.class_of.len()
    }

    fn valid(&self, o: u32) -> bool {
        o != NO_OBJECT && (o as usize) < self.num_objects()
    }
}

/// The regions that survive step 2, grouped by under-segmentation (step 4).
struct Groups {
    /// Objects that were "missed" (dropped small regions).
    dropped: Vec<bool>,
    /// Members of each group, ordered by their smallest object id.
    list: Vec<Vec<u32>>,
    /// Group of each object (`usize::MAX` for none).
    of: Vec<usize>,
}

impl Groups {
    fn kept(&self, input: &ViewInput<'_>, o: u32) -> bool {
        input.valid(o) && !self.dropped[o as usize]
    }
}

/// The provisional (pre-jitter) masks of step 5.
struct Provisional {
    /// (centroid, normal) of the splitting line per group, or None.
    lines: Vec<Option<([f64; 2], [f64; 2])>>,
    /// (group, half) of each provisional mask.
    masks: Vec<(usize, Option<u8>)>,
    /// Provisional mask per pixel, `NONE` = none.
    labels: Vec<u32>,
}

/// Derives the masks of view `view` from its object-id map (`ids`, row-major W×H).
/// `class_of[o]` is the class id of object o. Deterministic: every random decision is
/// keyed by (seed, view, object) or (seed, view, pixel).
pub(crate) fn view_masks(
    config: &Config,
    view: usize,
    ids: &[u32],
    width: usize,
    class_of: &[u32],
    protos: &Prototypes,
) -> ViewMasks {
    let input = ViewInput {
        config,
        seed: config.seed,
        v: view as u64,
        ids,
        width,
        height: ids.len() / width.max(1),
        class_of,
    };
    let mut prov = ViewProvenance {
        view,
        ..Default::default()
    };
    let groups = group_regions(&input, &mut prov);
    let provisional = split_groups(&input, &groups);
    let l1 = jitter_boundaries(&input, &provisional.labels, &mut prov);
    let (labels, masks) = final_masks(&input, &groups, &provisional, &l1, protos, &mut prov);
    prov.split = provisional.lines.iter().filter(|l| l.is_some()).count();
    prov.masks = masks.len();
    ViewMasks {
        labels,
        masks,
        provenance: prov,
    }
}

/// Steps 1-4: object regions, missed small objects, and under-segmentation (a region
/// merged with a neighbour sharing a boundary, 4-adjacency).
fn group_regions(input: &ViewInput<'_>, prov: &mut ViewProvenance) -> Groups {
    let (fm, seed, v) = (input.faults(), input.seed, input.v);
    let (ids, width, height, n_obj) = (input.ids, input.width, input.height, input.num_objects());
    let mut area = vec![0u64; n_obj];
    for &o in ids {
        if input.valid(o) {
            area[o as usize] += 1;
        }
    }
    let regions: Vec<usize> = (0..n_obj).filter(|&o| area[o] > 0).collect();
    prov.visible_objects = regions.len();

    let mut dropped = vec![false; n_obj];
    for &o in &regions {
        if area[o] < u64::from(fm.min_area_px)
            && unit(&[seed, tag::DROP, v, o as u64]) < fm.p_miss_small
        {
            dropped[o] = true;
            prov.dropped_small += 1;
        }
    }
    let kept = |o: u32| input.valid(o) && !dropped[o as usize];

    let mut adjacent = BTreeSet::new();
    if fm.p_merge > 0.0 {
        for y in 0..height {
            for x in 0..width {
                let a = ids[y * width + x];
                let right = (x + 1 < width).then(|| ids[y * width + x + 1]);
                let down = (y + 1 < height).then(|| ids[(y + 1) * width + x]);
                for b in [right, down].into_iter().flatten() {
                    if a != b && kept(a) && kept(b) {
                        adjacent.insert((a.min(b), a.max(b)));
                        adjacent.insert((a.max(b), a.min(b)));
                    }
                }
            }
        }
    }
    let mut uf = UnionFind((0..n_obj).collect());
    for &o in &regions {
        if dropped[o] || fm.p_merge <= 0.0 || unit(&[seed, tag::MERGE, v, o as u64]) >= fm.p_merge {
            continue;
        }
        let nbrs: Vec<u32> = adjacent
            .range((o as u32, 0)..(o as u32 + 1, 0))
            .map(|p| p.1)
            .collect();
        if nbrs.is_empty() {
            continue;
        }
        let pick = nbrs
            [(unit(&[seed, tag::MERGE, v, o as u64, 1]) * nbrs.len() as f64) as usize % nbrs.len()];
        if uf.union(o, pick as usize) {
            prov.merged += 1;
        }
    }

    // Groups keyed by their smallest object id: roots are the smallest member (union
    // keeps the smaller root), so the BTreeMap is ordered by key object.
    let mut groups: BTreeMap<usize, Vec<u32>> = BTreeMap::new();
    for &o in &regions {
        if !dropped[o] {
            groups.entry(uf.find(o)).or_default().push(o as u32);
        }
    }
    let list: Vec<Vec<u32>> = groups.into_values().collect();
    let mut of = vec![usize::MAX; n_obj];
    for (g, members) in list.iter().enumerate() {
        for &o in members {
            of[o as usize] = g;
        }
    }
    Groups { dropped, list, of }
}

/// Step 5, over-segmentation: a group is split in two by a random line through its
/// centroid.
fn split_groups(input: &ViewInput<'_>, groups: &Groups) -> Provisional {
    let (fm, seed, v) = (input.faults(), input.seed, input.v);
    let (ids, width, height) = (input.ids, input.width, input.height);
    let mut sums = vec![[0.0f64; 3]; groups.list.len()];
    for y in 0..height {
        for x in 0..width {
            let o = ids[y * width + x];
            if groups.kept(input, o) {
                let s = &mut sums[groups.of[o as usize]];
                s[0] += x as f64 + 0.5;
                s[1] += y as f64 + 0.5;
                s[2] += 1.0;
            }
        }
    }
    let lines: Vec<Option<([f64; 2], [f64; 2])>> = groups
        .list
        .iter()
        .enumerate()
        .map(|(g, members)| {
            let k = u64::from(members[0]);
            if fm.p_split <= 0.0
                || unit(&[seed, tag::SPLIT, v, k]) >= fm.p_split
                || sums[g][2] < 2.0
            {
                return None;
            }
            let a = std::f64::consts::TAU * unit(&[seed, tag::SPLIT, v, k, 1]);
            Some((
                [sums[g][0] / sums[g][2], sums[g][1] / sums[g][2]],
                [a.cos(), a.sin()],
            ))
        })
        .collect();
    let mut first_mask = Vec::with_capacity(groups.list.len());
    let mut masks: Vec<(usize, Option<u8>)> = Vec::new();
    for (g, line) in lines.iter().enumerate() {
        first_mask.push(masks.len() as u32);
        if line.is_some() {
            masks.push((g, Some(0)));
            masks.push((g, Some(1)));
        } else {
            masks.push((g, None));
        }
    }
    let mut labels = vec![NONE; ids.len()];
    for y in 0..height {
        for x in 0..width {
            let o = ids[y * width + x];
            if !groups.kept(input, o) {
                continue;
            }
            let g = groups.of[o as usize];
            let side = match &lines[g] {
                Some((c, n)) => {
                    u32::from((x as f64 + 0.5 - c[0]) * n[0] + (y as f64 + 0.5 - c[1]) * n[1] > 0.0)
                }
                None => 0,
            };
            labels[y * width + x] = first_mask[g] + side;
        }
    }
    Provisional {
        lines,
        masks,
        labels,
    }
}

/// Step 6: boundary jitter and unassigned boundary pixels, both decided on the
/// pre-jitter map `l0`.
fn jitter_boundaries(input: &ViewInput<'_>, l0: &[u32], prov: &mut ViewProvenance) -> Vec<u32> {
    let (fm, seed, v) = (input.faults(), input.seed, input.v);
    let (width, height) = (input.width, input.height);
    let mut l1 = l0.to_vec();
    if fm.p_jitter <= 0.0 && fm.p_unassigned <= 0.0 {
        return l1;
    }
    let r = fm.jitter_px as i64;
    let mut others: Vec<u32> = Vec::new();
    for y in 0..height {
        for x in 0..width {
            let i = y * width + x;
            let here = l0[i];
            let p = i as u64;
            if fm.p_jitter > 0.0 && r > 0 {
                others.clear();
                for dy in -r..=r {
                    for dx in -r..=r {
                        let (xx, yy) = (x as i64 + dx, y as i64 + dy);
                        if xx < 0 || yy < 0 || xx >= width as i64 || yy >= height as i64 {
                            continue;
                        }
                        let l = l0[yy as usize * width + xx as usize];
                        if l != here && !others.contains(&l) {
                            others.push(l);
                        }
                    }
                }
                if !others.is_empty() && unit(&[seed, tag::JITTER, v, p]) < fm.p_jitter {
                    let k = (unit(&[seed, tag::JITTER, v, p, 1]) * others.len() as f64) as usize;
                    l1[i] = others[k.min(others.len() - 1)];
                    prov.jittered_px += 1;
                }
            }
            if fm.p_unassigned > 0.0 {
                let boundary = (x > 0 && l0[i - 1] != here)
                    || (x + 1 < width && l0[i + 1] != here)
                    || (y > 0 && l0[i - width] != here)
                    || (y + 1 < height && l0[i + width] != here);
                if boundary
                    && l1[i] != NONE
                    && unit(&[seed, tag::UNASSIGNED, v, p]) < fm.p_unassigned
                {
                    l1[i] = NONE;
                    prov.unassigned_px += 1;
                }
            }
        }
    }
    l1
}

/// Step 7: the final masks (empty ones dropped, renumbered in provisional order), their
/// view-local label map (`u16::MAX` = none) and each mask's composition and feature.
fn final_masks(
    input: &ViewInput<'_>,
    groups: &Groups,
    provisional: &Provisional,
    l1: &[u32],
    protos: &Prototypes,
    prov: &mut ViewProvenance,
) -> (Vec<u16>, Vec<MaskInfo>) {
    let np = provisional.masks.len();
    let mut final_count = vec![0u64; np];
    for &l in l1 {
        if l != NONE {
            final_count[l as usize] += 1;
        }
    }
    let mut new_index = vec![u16::MAX; np];
    let mut next = 0u16;
    for (m, c) in final_count.iter().enumerate() {
        if *c > 0 && next < u16::MAX {
            new_index[m] = next;
            next += 1;
        }
    }
    let labels: Vec<u16> = l1
        .iter()
        .map(|&l| {
            if l == NONE {
                u16::MAX
            } else {
                new_index[l as usize]
            }
        })
        .collect();
    prov.no_mask_px = labels.iter().filter(|&&l| l == u16::MAX).count() as u64;

    // Compositions: intended (pre-jitter, by class) for the feature, final (by object)
    // for purity.
    let mut intended: Vec<BTreeMap<u32, u64>> = vec![BTreeMap::new(); np];
    let mut actual: Vec<BTreeMap<u32, u64>> = vec![BTreeMap::new(); np];
    for (i, (&a, &b)) in provisional.labels.iter().zip(l1).enumerate() {
        let o = input.ids[i];
        if a != NONE && input.valid(o) {
            *intended[a as usize]
                .entry(input.class_of[o as usize])
                .or_default() += 1;
        }
        if b != NONE {
            *actual[b as usize].entry(o).or_default() += 1;
        }
    }

    let mut masks = Vec::with_capacity(next as usize);
    for m in 0..np {
        if new_index[m] == u16::MAX {
            continue;
        }
        let (g, half) = provisional.masks[m];
        let members = groups.list[g].clone();
        let key = [u64::from(members[0]), half.map_or(2, u64::from)];
        let pixels = final_count[m];
        let (object, count) =
            actual[m].iter().fold(
                (NO_OBJECT, 0u64),
                |best, (o, c)| if *c > best.1 { (*o, *c) } else { best },
            );
        let purity = count as f64 / pixels.max(1) as f64;
        let (feature, class_id, wrong_class) =
            mask_feature(input.config, input.v, key, &intended[m], protos);
        if wrong_class.is_some() {
            prov.wrong_class += 1;
        }
        masks.push(MaskInfo {
            objects: members,
            half,
            pixels,
            object,
            purity,
            class_id,
            wrong_class,
            feature,
        });
    }
    (labels, masks)
}

/// The feature of one mask: normalize(mix + noise), mix = area-weighted mean of the
/// class prototypes of its intended composition, possibly biased toward another class.
fn mask_feature(
    config: &Config,
    view: u64,
    key: [u64; 2],
    composition: &BTreeMap<u32, u64>,
    protos: &Prototypes,
) -> (Vec<f32>, u32, Option<u32>) {
    let fm = &config.faults;
    let d = protos.dim();
    let mut mix = vec![0.0; d];
    let mut dominant = (0u32, 0u64);
    for (&class, &count) in composition {
        if let Some(p) = protos.of_class(class) {
            mix.iter_mut()
                .zip(p)
                .for_each(|(m, x)| *m += count as f64 * x);
        }
        if count > dominant.1 {
            dominant = (class, count);
        }
    }
    let mut f = normalized(mix);
    let seed = config.seed;
    let mut wrong = None;
    if fm.p_wrong_class > 0.0
        && unit(&[seed, tag::WRONG_CLASS, view, key[0], key[1]]) < fm.p_wrong_class
    {
        let others: Vec<(u32, &[f64])> = protos
            .classes()
            .filter(|c| c.0 != dominant.0)
            .map(|c| (c.0, c.2))
            .collect();
        if !others.is_empty() {
            let mut rng = Rng::new(&[seed, tag::WRONG_CLASS, view, key[0], key[1], 1]);
            let (other, p) = others[rng.below(others.len())];
            let [lo, hi] = fm.wrong_class_beta;
            let beta = rng.range(lo, hi);
            f.iter_mut()
                .zip(p)
                .for_each(|(a, b)| *a = (1.0 - beta) * *a + beta * b);
            wrong = Some(other);
        }
    }
    let mut rng = Rng::new(&[seed, tag::FEATURE, view, key[0], key[1]]);
    let area = composition.values().sum::<u64>().max(1) as f64;
    let crop = (fm.crop_noise_px / area).max(1.0).sqrt();
    let f = noisy(f, fm.feature_noise * crop, &mut rng);
    let f = if f.iter().all(|x| *x == 0.0) {
        protos
            .of_class(dominant.0)
            .map_or_else(|| unit_vector(d), <[f64]>::to_vec)
    } else {
        f
    };
    (f.iter().map(|x| *x as f32).collect(), dominant.0, wrong)
}

fn unit_vector(d: usize) -> Vec<f64> {
    let mut v = vec![0.0; d];
    if let Some(x) = v.first_mut() {
        *x = 1.0;
    }
    v
}

/// The prompt table: (name, embedding, class id) for every scene class, then the
/// distractors, then the canonical negatives.
pub(crate) fn prompts(config: &Config, protos: &Prototypes) -> Vec<(String, Vec<f32>, i32)> {
    let (seed, d, sigma) = (config.seed, protos.dim(), config.faults.text_noise);
    let mut out: Vec<(String, Vec<f32>, i32)> = Vec::new();
    let mut all: Vec<Vec<f64>> = Vec::new();
    let emb = |name: &str, base: Vec<f64>| {
        let mut rng = Rng::new(&[seed, tag::PROMPT, name_hash(name)]);
        noisy(base, sigma, &mut rng)
            .iter()
            .map(|x| *x as f32)
            .collect::<Vec<f32>>()
    };
    for (id, name, p) in protos.classes() {
        all.push(p.to_vec());
        out.push((name.to_string(), emb(name, p.to_vec()), id as i32));
    }
    for name in &config.distractors {
        if out.iter().any(|o| &o.0 == name) || CANONICAL_NEGATIVES.contains(&name.as_str()) {
            continue;
        }
        let p = prototype(seed, d, name);
        all.push(p.clone());
        out.push((name.clone(), emb(name, p), -1));
    }
    let mut mean = vec![0.0; d];
    for p in &all {
        mean.iter_mut()
            .zip(p)
            .for_each(|(m, x)| *m += x / all.len() as f64);
    }
    for name in CANONICAL_NEGATIVES {
        if out.iter().any(|o| o.0 == name) {
            continue;
        }
        out.push((name.to_string(), emb(name, mean.clone()), -1));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Preset;

    fn setup(faults: FaultModel) -> (Config, Prototypes, Vec<u32>, Vec<u32>) {
        let mut c = Config::preset(Preset::Tiny, 3);
        c.faults = faults;
        let protos = Prototypes::new(
            3,
            16,
            &[
                (1, "wall".into()),
                (2, "floor".into()),
                (3, "cabinet".into()),
            ],
        );
        // 8x6 map: left half object 0 (wall), right half object 1 (floor), a 2x2 object 2.
        let (w, h) = (8usize, 6usize);
        let mut ids = vec![0u32; w * h];
        for y in 0..h {
            for x in 4..w {
                ids[y * w + x] = 1;
            }
        }
        for (x, y) in [(1, 1), (2, 1), (1, 2), (2, 2)] {
            ids[y * w + x] = 2;
        }
        (c, protos, ids, vec![1, 2, 3])
    }

    #[test]
    fn exact_masks_equal_regions() {
        let (c, protos, ids, class_of) = setup(FaultModel::exact());
        let m = view_masks(&c, 0, &ids, 8, &class_of, &protos);
        assert_eq!(m.masks.len(), 3);
        for (p, l) in ids.iter().zip(&m.labels) {
            assert_eq!(u32::from(*l), *p);
        }
        assert!(m.masks.iter().all(|k| k.purity == 1.0));
        assert_eq!(m.masks[2].pixels, 4);
        assert_eq!(m.masks[2].class_id, 3);
    }

    #[test]
    fn certain_faults_fire() {
        let faults = FaultModel {
            min_area_px: 5,
            p_miss_small: 1.0,
            p_merge: 1.0,
            p_split: 0.0,
            p_jitter: 0.0,
            p_unassigned: 0.0,
            ..FaultModel::exact()
        };
        let (c, protos, ids, class_of) = setup(faults);
        let m = view_masks(&c, 0, &ids, 8, &class_of, &protos);
        // Object 2 dropped, 0 and 1 merged into one mask.
        assert_eq!(m.provenance.dropped_small, 1);
        assert_eq!(m.masks.len(), 1);
        assert_eq!(m.masks[0].objects, vec![0, 1]);
        assert_eq!(m.labels.iter().filter(|l| **l == u16::MAX).count(), 4);
        let split = FaultModel {
            p_split: 1.0,
            ..FaultModel::exact()
        };
        let (c, protos, ids, class_of) = setup(split);
        let m = view_masks(&c, 0, &ids, 8, &class_of, &protos);
        assert_eq!(m.masks.len(), 6);
        assert_eq!(m.masks.iter().map(|k| k.pixels).sum::<u64>(), 48);
    }
}
