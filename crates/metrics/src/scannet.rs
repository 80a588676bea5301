//! ScanNet open-vocabulary point-cloud understanding (paper §4.3, Table 2), with
//! OpenGaussian's protocol: per-vertex NYU40 predictions against the mesh's ground truth,
//! restricted to a class set of 19, 15 or 10 classes.
//!
//! Definitions, for a class set S and the vertices v whose ground truth g(v) ∈ S (all
//! other vertices, including unannotated ones with label 0, are ignored entirely):
//!
//! * TP_c = #{v : g(v) = c, p(v) = c}, FN_c = #{v : g(v) = c, p(v) ≠ c},
//!   FP_c = #{v : g(v) ≠ c, p(v) = c}.
//!   A prediction outside S or −1 (no label) equals no class of S, so it is a miss for
//!   its vertex and a false positive of nothing.
//! * IoU_c = TP_c / (TP_c + FP_c + FN_c), Acc_c = TP_c / (TP_c + FN_c) (recall).
//! * mIoU, mAcc = means over the classes of S *present in the ground truth*
//!   (TP_c + FN_c ≥ 1); classes of S absent from the scene are listed with `gt_count = 0`
//!   and do not count, even if predicted.
//!
//! Every score is in percent (0..100), as the paper's tables. With no class of S present
//! the means are NaN (`null` in JSON).

use profuse_formats::label_space::{nyu40_name, SCANNET_10, SCANNET_15, SCANNET_19};
use profuse_formats::Mesh;
use serde::Serialize;

use crate::{invalid, MetricsError, Result};

/// The NYU40 class names; id `i` (1-based) is `NYU40_NAMES[i - 1]`.
pub use profuse_formats::label_space::NYU40 as NYU40_NAMES;

/// The 19 classes of OpenGaussian's ScanNet protocol.
pub const CLASSES_19: [u32; 19] = SCANNET_19;
/// The 15-class subset.
pub const CLASSES_15: [u32; 15] = SCANNET_15;
/// The 10-class subset.
pub const CLASSES_10: [u32; 10] = SCANNET_10;
/// Every NYU40 class (not a paper setting; useful for synthetic scenes, whose ceiling 22
/// and lamp 35 are in none of the paper's sets).
pub const CLASSES_40: [u32; 40] = {
    let mut ids = [0u32; 40];
    let mut i = 0;
    while i < 40 {
        ids[i] = i as u32 + 1;
        i += 1;
    }
    ids
};

/// A class set of the protocol.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
pub enum ClassSet {
    /// [`CLASSES_19`].
    Nyu19,
    /// [`CLASSES_15`].
    Nyu15,
    /// [`CLASSES_10`].
    Nyu10,
    /// [`CLASSES_40`].
    Nyu40,
}

impl ClassSet {
    /// The paper's three settings, in its table's order.
    pub const PAPER: [ClassSet; 3] = [ClassSet::Nyu19, ClassSet::Nyu15, ClassSet::Nyu10];

    /// The NYU40 ids of the set, ascending.
    pub fn ids(self) -> &'static [u32] {
        match self {
            ClassSet::Nyu19 => &CLASSES_19,
            ClassSet::Nyu15 => &CLASSES_15,
            ClassSet::Nyu10 => &CLASSES_10,
            ClassSet::Nyu40 => &CLASSES_40,
        }
    }

    /// `"19"`, `"15"`, `"10"` or `"40"`.
    pub fn name(self) -> &'static str {
        match self {
            ClassSet::Nyu19 => "19",
            ClassSet::Nyu15 => "15",
            ClassSet::Nyu10 => "10",
            ClassSet::Nyu40 => "40",
        }
    }

    /// Parses `"19"`, `"15"`, `"10"` or `"40"`.
    pub fn parse(text: &str) -> Option<ClassSet> {
        [
            ClassSet::Nyu19,
            ClassSet::Nyu15,
            ClassSet::Nyu10,
            ClassSet::Nyu40,
        ]
        .into_iter()
        .find(|s| s.name() == text)
    }
}

/// The NYU40 name of a class id (`None` outside 1..=40).
pub fn class_name(id: u32) -> Option<&'static str> {
    nyu40_name(id)
}

/// One class of the per-class table.
#[derive(Debug, Clone, Serialize)]
pub struct ClassRow {
    /// NYU40 id.
    pub id: u32,
    /// NYU40 name.
    pub name: &'static str,
    /// IoU in percent; NaN (`null`) when the class is neither present nor predicted.
    pub iou: f64,
    /// Recall in percent; NaN (`null`) when the class is not present.
    pub acc: f64,
    /// Evaluated vertices whose ground truth is this class (TP + FN).
    pub gt_count: u64,
    /// Evaluated vertices predicted as this class (TP + FP).
    pub pred_count: u64,
    /// Vertices of this class predicted correctly (TP).
    pub correct: u64,
    /// The false positives by ground-truth class: evaluated vertices of another class of
    /// the set predicted as this one (FP_c split by g), most first (ties: smaller id),
    /// non-zero counts only. Their counts sum to `pred_count − correct`.
    pub false_positives: Vec<Confusion>,
    /// The misses by prediction: this class's vertices predicted as another class of the
    /// set, or (id −1, name `none`) with no label or a label outside the set (FN_c split
    /// by p), most first (ties: smaller id), non-zero only. Their counts sum to
    /// `gt_count − correct`.
    pub missed_as: Vec<Confusion>,
}

/// One cell of the confusion between two classes (see [`ClassRow::false_positives`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Confusion {
    /// NYU40 id; −1 for no label or one outside the set.
    pub id: i32,
    /// NYU40 name (`none` for −1).
    pub name: &'static str,
    /// Vertices.
    pub count: u64,
}

/// The non-zero `(slot, count)` cells as [`Confusion`]s, most first, ties by id; slot
/// `ids.len()` is "none".
fn confusions(cells: impl Iterator<Item = (usize, u64)>, ids: &[u32]) -> Vec<Confusion> {
    let mut out: Vec<Confusion> = cells
        .filter(|&(_, n)| n > 0)
        .map(|(k, count)| match ids.get(k) {
            Some(&id) => Confusion {
                id: id as i32,
                name: class_name(id).unwrap_or("?"),
                count,
            },
            None => Confusion {
                id: -1,
                name: "none",
                count,
            },
        })
        .collect();
    out.sort_by(|a, b| b.count.cmp(&a.count).then(a.id.cmp(&b.id)));
    out
}

/// Scores of one scene under one class set.
#[derive(Debug, Clone, Serialize)]
pub struct ScannetScores {
    /// The class set (`"19"`, `"15"`, `"10"`, `"40"`).
    pub set: &'static str,
    /// Mean IoU over the present classes, percent.
    pub miou: f64,
    /// Mean per-class recall over the present classes, percent.
    pub macc: f64,
    /// Classes of the set present in the ground truth (the denominator of the means).
    pub classes_present: usize,
    /// Vertices evaluated (ground truth in the set).
    pub evaluated: u64,
    /// Vertices ignored (ground truth outside the set or unannotated).
    pub ignored: u64,
    /// Evaluated vertices predicted correctly.
    pub correct: u64,
    /// Evaluated vertices with no prediction in the set (−1 or another class id).
    pub unlabelled_or_outside: u64,
    /// Every class of the set, ascending id (absent classes have `gt_count = 0`).
    pub per_class: Vec<ClassRow>,
}

fn percent(num: u64, den: u64) -> f64 {
    if den == 0 {
        f64::NAN
    } else {
        100.0 * num as f64 / den as f64
    }
}

/// Evaluates per-vertex predictions (`−1` = no label) against ground-truth NYU40 labels
/// (`0` = unannotated) under a class set. See the module documentation for the formulas.
///
/// ```
/// use profuse_metrics::scannet::{evaluate, ClassSet};
/// // wall wall floor chair | unannotated, ceiling (22: not in the set) are ignored
/// let truth = [1, 1, 2, 5, 0, 22];
/// let pred = [1, 2, 2, -1, 7, 22];
/// let s = evaluate(&pred, &truth, ClassSet::Nyu10).unwrap();
/// assert_eq!((s.classes_present, s.evaluated, s.ignored), (3, 4, 2));
/// // wall 1/2, floor 1/2 (one false positive), chair 0/1
/// assert!((s.miou - 100.0 / 3.0).abs() < 1e-9);
/// assert!((s.macc - 50.0).abs() < 1e-9);
/// // The floor's false positive is a wall vertex; the chair was missed with no label.
/// let (wall, floor, chair) = (&s.per_class[0], &s.per_class[1], &s.per_class[3]);
/// assert_eq!((floor.false_positives[0].name, floor.false_positives[0].count), ("wall", 1));
/// assert_eq!((wall.missed_as[0].name, chair.missed_as[0].id), ("floor", -1));
/// ```
pub fn evaluate(pred: &[i32], truth: &[u32], set: ClassSet) -> Result<ScannetScores> {
    if pred.len() != truth.len() {
        return Err(MetricsError::LengthMismatch {
            what: "ScanNet evaluation",
            left_name: "predicted vertex labels",
            left: pred.len(),
            right_name: "ground-truth mesh labels",
            right: truth.len(),
        });
    }
    let ids = set.ids();
    // NYU40 id -> row index in the set, for ids 0..=40 (everything else is outside).
    let mut slot = [usize::MAX; 41];
    for (k, &id) in ids.iter().enumerate() {
        slot[id as usize] = k;
    }
    let slot_of = |id: i64| -> Option<usize> {
        usize::try_from(id)
            .ok()
            .and_then(|i| slot.get(i).copied())
            .filter(|&k| k != usize::MAX)
    };
    let c = ids.len();
    // confusion[g][p]: ground-truth slot g, predicted slot p (slot c: none or outside).
    let mut confusion = vec![vec![0u64; c + 1]; c];
    let mut evaluated = 0u64;
    for (&p, &g) in pred.iter().zip(truth) {
        let Some(gk) = slot_of(i64::from(g)) else {
            continue;
        };
        evaluated += 1;
        confusion[gk][slot_of(i64::from(p)).unwrap_or(c)] += 1;
    }
    let gt: Vec<u64> = confusion.iter().map(|row| row.iter().sum()).collect();
    let predicted: Vec<u64> = (0..c)
        .map(|k| confusion.iter().map(|row| row[k]).sum())
        .collect();
    let correct: Vec<u64> = (0..c).map(|k| confusion[k][k]).collect();
    let outside: u64 = confusion.iter().map(|row| row[c]).sum();
    let per_class: Vec<ClassRow> = ids
        .iter()
        .enumerate()
        .map(|(k, &id)| ClassRow {
            id,
            name: class_name(id).unwrap_or("?"),
            iou: percent(correct[k], gt[k] + predicted[k] - correct[k]),
            acc: percent(correct[k], gt[k]),
            gt_count: gt[k],
            pred_count: predicted[k],
            correct: correct[k],
            false_positives: confusions(
                (0..c).filter(|&g| g != k).map(|g| (g, confusion[g][k])),
                ids,
            ),
            missed_as: confusions(
                (0..=c).filter(|&p| p != k).map(|p| (p, confusion[k][p])),
                ids,
            ),
        })
        .collect();
    let present: Vec<&ClassRow> = per_class.iter().filter(|r| r.gt_count > 0).collect();
    let mean = |f: fn(&ClassRow) -> f64| {
        if present.is_empty() {
            f64::NAN
        } else {
            present.iter().map(|r| f(r)).sum::<f64>() / present.len() as f64
        }
    };
    Ok(ScannetScores {
        set: set.name(),
        miou: mean(|r| r.iou),
        macc: mean(|r| r.acc),
        classes_present: present.len(),
        evaluated,
        ignored: truth.len() as u64 - evaluated,
        correct: correct.iter().sum(),
        unlabelled_or_outside: outside,
        per_class,
    })
}

/// Means of mIoU and mAcc over scenes (the paper averages per-scene scores), per set.
#[derive(Debug, Clone, Serialize)]
pub struct ScannetMean {
    /// The class set.
    pub set: &'static str,
    /// Mean of the scenes' mIoU, percent.
    pub miou: f64,
    /// Mean of the scenes' mAcc, percent.
    pub macc: f64,
    /// Scenes averaged (those with at least one present class).
    pub scenes: usize,
}

/// Averages per-scene scores of one class set; scenes without any present class are
/// skipped. Errors when the scores are of different sets.
pub fn mean_over_scenes(scenes: &[ScannetScores]) -> Result<ScannetMean> {
    let set = scenes.first().map_or("", |s| s.set);
    if let Some(other) = scenes.iter().find(|s| s.set != set) {
        return Err(invalid(
            "<memory>",
            "set",
            format!("cannot average class set {} with {set}", other.set),
        ));
    }
    let used: Vec<&ScannetScores> = scenes.iter().filter(|s| s.classes_present > 0).collect();
    let avg = |f: fn(&ScannetScores) -> f64| {
        if used.is_empty() {
            f64::NAN
        } else {
            used.iter().map(|s| f(s)).sum::<f64>() / used.len() as f64
        }
    };
    Ok(ScannetMean {
        set,
        miou: avg(|s| s.miou),
        macc: avg(|s| s.macc),
        scenes: used.len(),
    })
}

/// The per-vertex ground-truth NYU40 labels of a mesh (`file` names it in the error when
/// it has none). Any source works: `Mesh::read` for a mesh file (SPEC.md §4.12), or
/// `scene_io::scannet::read_labelled_mesh` for ScanNet's PLY and NumPy exports too.
pub fn ground_truth_labels(mesh: &Mesh, file: impl std::fmt::Display) -> Result<Vec<u32>> {
    match &mesh.labels {
        Some(labels) => Ok(labels.to_vec()),
        None => Err(invalid(
            file,
            "labels",
            "the mesh has no per-vertex ground-truth labels",
        )),
    }
}
