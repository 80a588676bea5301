//! Small valid examples of every file kind, and the golden vectors of SPEC.md: these
//! files plus one-defect mutations of them that every reader must reject with a known
//! error code and field. `cargo run -p profuse-formats --example write_vectors` writes
//! them to `formats/vectors/`; a test checks that the committed files equal these bytes.

use std::collections::BTreeMap;

use half::f16;
use serde_json::{json, Value};

use crate::check::{Floats, Labels};
use crate::container::{Container, Dtype};
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;
use crate::{
    Cameras, Features, FuseGrouping, FuseOrphans, FusePartial, Gaussians, Masks, Matches, Mesh, Pq,
    Prompts, Proposals, Selection, SemanticIndex, SparseMatches, TopK, VertexLabels, ViewMaps,
    WarpCoords, WarpPartial,
};

/// Two views looking at the origin from +x and −z, 8x6 pixels.
pub fn cameras() -> Cameras {
    // View 0: identity rotation, camera at (0, 0, -4). View 1: rotated 90° about y.
    let w2c = vec![
        [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 4.0],
        [0.0, 0.0, -1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 4.0],
    ];
    Cameras {
        image_names: vec!["images/a.png".into(), "images/b.png".into()],
        image_size: vec![[8, 6], [8, 6]].into(),
        intrinsics: vec![[10.0, 10.0, 4.0, 3.0], [12.0, 11.0, 4.5, 3.0]].into(),
        world_to_camera: w2c.into(),
        distortion: Some(vec![[0.0; 4], [-0.01, 0.002, 0.0005, -0.0003]].into()),
        extra: BTreeMap::from([("generator".to_string(), "samples".to_string())]),
    }
}

/// Four Gaussians with SH degree 1 and class ids.
pub fn gaussians() -> Gaussians {
    Gaussians {
        means: vec![
            [0.0, 0.0, 0.0],
            [0.5, -0.25, 1.0],
            [-1.0, 2.0, 0.125],
            [3.0, 0.0, -2.0],
        ]
        .into(),
        log_scales: vec![
            [-2.0, -2.0, -2.0],
            [-1.5, -3.0, -2.5],
            [0.0, 0.0, 0.0],
            [-4.0, -4.0, -1.0],
        ]
        .into(),
        rotations: vec![
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.5, 0.5, 0.5, 0.5],
            [2.0, 0.0, 0.0, 0.0],
        ]
        .into(),
        opacity_logits: vec![0.0, 2.0, -1.0, 20.0].into(),
        sh_dc: vec![
            [0.1, 0.2, 0.3],
            [-0.5, 0.0, 0.5],
            [1.0, 1.0, 1.0],
            [0.0, 0.0, 0.0],
        ]
        .into(),
        sh_degree: 1,
        sh_rest: Some(
            (0..4 * 3 * 3)
                .map(|i| i as f32 * 0.01 - 0.1)
                .collect::<Vec<f32>>()
                .into(),
        ),
        class_ids: Some(vec![0, 1, -1, 2].into()),
        extra: BTreeMap::new(),
    }
}

fn unit_rows(rows: &[[f32; 4]]) -> Vec<f32> {
    rows.iter()
        .flat_map(|r| {
            let n = r.iter().map(|v| v * v).sum::<f32>().sqrt();
            r.map(|v| v / n)
        })
        .collect()
}

fn mask_features() -> Vec<f32> {
    unit_rows(&[
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 1.0, 0.0],
        [1.0, 2.0, 3.0, 4.0],
        [0.0, 0.0, 0.0, 1.0],
        [0.5, -0.5, 0.5, -0.5],
    ])
}

/// Two views of 4x3 label maps with 3 + 2 masks, U16 labels and F16 features.
pub fn masks() -> Masks {
    let n = u16::MAX;
    let labels: Vec<u16> = vec![
        0, 0, 1, 1, //
        0, 2, 2, n, //
        n, 2, 2, n, //
        1, 1, 0, 0, //
        1, 1, 0, n, //
        n, n, n, n,
    ];
    let feats = mask_features();
    Masks {
        view_names: vec!["images/a.png".into(), "images/b.png".into()],
        width: 4,
        height: 3,
        labels: Labels::U16(labels.into()),
        mask_offsets: vec![0, 3, 5].into(),
        features: Floats::F16(
            feats
                .into_iter()
                .map(f16::from_f32)
                .collect::<Vec<_>>()
                .into(),
        ),
        dim: 4,
        extra: BTreeMap::new(),
    }
}

/// The same masks with U32 labels and F32 features.
pub fn masks_wide() -> Masks {
    let m = masks();
    let labels: Vec<u32> = (0..m.labels.len())
        .map(|i| m.labels.get(i).unwrap_or(u32::MAX))
        .collect();
    Masks {
        labels: Labels::U32(labels.into()),
        features: Floats::F32(mask_features().into()),
        ..m
    }
}

/// Two ordered pairs (0, 1), (1, 0) on a 2x3 grid, normalized coordinates.
pub fn matches() -> Matches {
    let cells = 2 * 2 * 3;
    Matches {
        num_views: 2,
        pairs: vec![[0, 1], [1, 0]].into(),
        height: 2,
        width: 3,
        warp: Floats::F32(
            (0..cells * 2)
                .map(|i| (i as f32 / 12.0) - 1.0)
                .collect::<Vec<_>>()
                .into(),
        ),
        certainty: Floats::F32(
            (0..cells)
                .map(|i| (i % 5) as f32 / 4.0)
                .collect::<Vec<_>>()
                .into(),
        ),
        coords: WarpCoords::Normalized,
        extra: BTreeMap::new(),
    }
}

/// The same matches stored as F16, in pixel coordinates.
pub fn matches_half() -> Matches {
    let m = matches();
    let half = |f: &Floats| {
        Floats::F16(
            f.to_f32_vec()
                .into_iter()
                .map(f16::from_f32)
                .collect::<Vec<_>>()
                .into(),
        )
    };
    Matches {
        warp: half(&m.warp),
        certainty: half(&m.certainty),
        coords: WarpCoords::Pixels,
        ..m
    }
}

/// Two pairs with 3 + 2 matches.
pub fn sparse_matches() -> SparseMatches {
    SparseMatches {
        num_views: 3,
        pairs: vec![[0, 1], [2, 0]].into(),
        pair_offsets: vec![0, 3, 5].into(),
        points_i: vec![[0.5, 0.5], [3.25, 2.0], [7.5, 5.5], [1.0, 1.0], [2.0, 2.5]].into(),
        points_j: vec![
            [1.5, 0.5],
            [4.0, 2.25],
            [6.5, 5.0],
            [0.75, 1.25],
            [2.5, 2.0],
        ]
        .into(),
        certainty: vec![1.0, 0.5, 0.25, 1.0, 0.75].into(),
        extra: BTreeMap::new(),
    }
}

/// Five masks in two proposals, one mask unassigned and attached to proposal 0 as its
/// instance (matches [`masks`]).
pub fn proposals() -> Proposals {
    Proposals {
        mask_proposal: vec![0, 1, u32::MAX, 1, 0].into(),
        proposal_size: vec![2, 2].into(),
        proposal_views: vec![2, 2].into(),
        mask_share: Some(vec![0.875, 1.0, 0.5, 0.75, 0.625].into()),
        mask_instance: Some(vec![0, 1, 0, 1, 0].into()),
        extra: BTreeMap::from([("tau_iou".to_string(), "0.2".to_string())]),
    }
}

/// Four Gaussians, three registered.
pub fn features() -> Features {
    let mut f = unit_rows(&[
        [1.0, 0.0, 0.0, 0.0],
        [1.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 0.0, 0.0],
        [1.0, -2.0, 2.0, 4.0],
    ]);
    f[8..12].fill(0.0);
    Features {
        features: Floats::F32(f.into()),
        dim: 4,
        valid: vec![1, 1, 0, 1].into(),
        weight_sum: Some(vec![0.5, 2.0, 0.0, 1e-3].into()),
        extra: BTreeMap::new(),
    }
}

/// M = 2 sub-quantisers of dsub = 2 over three vectors.
pub fn pq() -> Pq {
    let centroids: Vec<f32> = (0..2 * 256 * 2)
        .map(|i| ((i * 37 % 101) as f32 - 50.0) / 64.0)
        .collect();
    Pq {
        m: 2,
        dsub: 2,
        centroids: centroids.into(),
        codes: vec![0, 255, 17, 3, 0, 0].into(),
        norms: vec![1.0, 0.875, 0.0].into(),
        valid: vec![1, 1, 0].into(),
        extra: BTreeMap::from([("seed".to_string(), "7".to_string())]),
    }
}

/// Three prompts, one a canonical negative.
pub fn prompts() -> Prompts {
    Prompts {
        names: vec!["chair".into(), "red mug".into(), "object".into()],
        dim: 4,
        embeddings: unit_rows(&[
            [1.0, 0.1, 0.0, 0.0],
            [0.0, 1.0, 0.2, 0.0],
            [0.5, 0.5, 0.5, 0.5],
        ])
        .into(),
        class_ids: Some(vec![3, 7, -1].into()),
        extra: BTreeMap::new(),
    }
}

/// Three selected Gaussians out of ten.
pub fn selection() -> Selection {
    Selection {
        prompt: "red mug".into(),
        num_gaussians: 10,
        gaussian_ids: vec![1, 4, 9].into(),
        scores: vec![0.31, 0.27, 0.5].into(),
        extra: BTreeMap::from([
            ("score".to_string(), "cosine".to_string()),
            ("threshold".to_string(), "0.25".to_string()),
        ]),
    }
}

/// Five Gaussians over three proposals (one without a descriptor): two dominant, one
/// below `min_share`, one never registered, one on the descriptor-less proposal.
pub fn semantic_index() -> SemanticIndex {
    let mut table = unit_rows(&[[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 1.0, 0.0], [0.0; 4]]);
    table[8..12].fill(0.0);
    SemanticIndex {
        descriptors: Floats::F32(table.into()),
        dim: 4,
        index: SemanticIndex::index_of(3, &[Some(0), Some(1), Some(0), None, Some(2)]),
        share: Some(vec![255, 200, 100, 0, 128].into()),
        min_share: 128,
        extra: BTreeMap::from([("generator".to_string(), "profuse-fuse".to_string())]),
    }
}

/// The semantic_index sample and its defects.
fn semantic_index_case() -> Case {
    let si = semantic_index();
    let v = bytes_of(&unvalidated(&si));
    let mut inv = container_defects(&v, "share");
    inv.extend([
        (
            "missing_tensor",
            without_tensor(&v, "share"),
            "missing_tensor",
            Some("share"),
        ),
        (
            "dtype",
            retype(&v, "index", Dtype::U32),
            "dtype",
            Some("index"),
        ),
        ("shape", reshape(&v, "share", &[4]), "shape", Some("share")),
        (
            "metadata",
            with_meta(&si, "min_share", Some("256")),
            "metadata",
            Some("min_share"),
        ),
        (
            "out_of_range",
            mutated(&si, |s| {
                s.index = SemanticIndex::index_of(3, &[Some(0), Some(3), Some(0), None, Some(2)])
            }),
            "out_of_range",
            Some("index"),
        ),
        (
            "non_finite",
            mutated(&si, |s| {
                let mut t = s.descriptors.to_f32_vec();
                t[1] = f32::NAN;
                s.descriptors = Floats::F32(t.into());
            }),
            "non_finite",
            Some("descriptors"),
        ),
        (
            "descriptors",
            mutated(&si, |s| {
                let mut t = s.descriptors.to_f32_vec();
                t[0] = 0.5;
                s.descriptors = Floats::F32(t.into());
            }),
            "invalid",
            Some("descriptors"),
        ),
        (
            "invalid",
            mutated(&si, |s| {
                if let Some(share) = &mut s.share {
                    set(share, 3, 9)
                }
            }),
            "invalid",
            Some("share"),
        ),
    ]);
    Case {
        stem: "semantic_index",
        valid: v,
        invalid: inv,
    }
}

/// Five vertices, one unlabelled.
pub fn vertex_labels() -> VertexLabels {
    VertexLabels {
        labels: vec![1, 2, -1, 5, 1].into(),
        confidence: Some(vec![0.9, 0.5, 0.0, 1.0, 0.75].into()),
        extra: BTreeMap::from([("label_space".to_string(), "nyu40".to_string())]),
    }
}

/// A unit square of two triangles with labels.
pub fn mesh() -> Mesh {
    Mesh {
        vertices: vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 1.0, 0.0],
            [0.0, 1.0, 0.0],
        ]
        .into(),
        colors: Some(vec![[255, 0, 0], [0, 255, 0], [0, 0, 255], [128, 128, 128]].into()),
        faces: Some(vec![[0, 1, 2], [0, 2, 3]].into()),
        labels: Some(vec![1, 1, 2, 0].into()),
        instances: Some(vec![1, 1, 2, 0].into()),
        extra: BTreeMap::from([("label_space".to_string(), "nyu40".to_string())]),
    }
}

/// Two views of 3x2 depth and object-id maps.
pub fn view_maps() -> ViewMaps {
    ViewMaps {
        view_names: vec!["images/a.png".into(), "images/b.png".into()],
        num_objects: 3,
        width: 3,
        height: 2,
        depth: vec![1.0, 1.5, 2.0, 0.0, 2.5, 3.0, 4.0, 4.0, 4.25, 0.5, 0.75, 0.0].into(),
        object_ids: Some(vec![0, 0, 1, u32::MAX, 2, 2, 1, 1, 1, 0, 0, u32::MAX].into()),
        extra: BTreeMap::new(),
    }
}

/// A 3x2 view with K = 3 slots per pixel.
pub fn topk() -> TopK {
    let n = u32::MAX;
    TopK {
        num_gaussians: 7,
        width: 3,
        height: 2,
        k: 3,
        ids: vec![0, 1, 2, 3, n, n, n, n, n, 6, 5, 4, 2, n, n, 1, 0, n].into(),
        weights: vec![
            0.5, 0.25, 0.125, 0.9, 0.0, 0.0, 0.0, 0.0, 0.0, 0.4, 0.3, 0.2, 0.75, 0.0, 0.0, 0.5,
            0.5, 0.0,
        ]
        .into(),
        transmittance: vec![0.125, 0.1, 1.0, 0.1, 0.25, 0.0].into(),
        extra: BTreeMap::from([("view".to_string(), "0".to_string())]),
    }
}

/// A blend shard over views 0 and 2 of 3: 3 masks (mask 1 an ignored orphan), 4
/// Gaussians (Gaussian 1 never hit), 4 entries of W, one sum above 2^64.
pub fn fuse_partial() -> FusePartial {
    let n = u32::MAX;
    FusePartial {
        num_gaussians: 4,
        num_views: 3,
        k: 2,
        grouping: FuseGrouping::Blend {
            orphans: FuseOrphans::Ignore,
        },
        num_groups: 3,
        pixels: 10,
        hits: 15,
        views: vec![0, 2].into(),
        mask_group: vec![0, n, 2].into(),
        mask_proposal: Some(vec![0, n, 0].into()),
        mask_share: Some(vec![1.0, 0.5, 0.75].into()),
        mask_features: vec![1.0, 0.0, 0.6, 0.8, 0.0, 1.0].into(),
        dim: 2,
        mask_mass: vec![[5 << 40, 0], [0, 0], [7 << 40, 1]].into(),
        w_offsets: vec![0, 2, 2, 3, 4].into(),
        w_groups: vec![0, 2, 0, 2].into(),
        w_sums: vec![[3 << 40, 0], [1 << 40, 0], [2 << 40, 0], [0, 1]].into(),
        extra: BTreeMap::from([("weight_scale".to_string(), "2^-62".to_string())]),
    }
}

/// A warp-graph shard over view pairs 1 and 2 of 4 ({0, 2} and {1, 2} of 3 views, 6
/// masks): pair {0, 2} has two links, pair {1, 2} none.
pub fn warp_partial() -> WarpPartial {
    let input = |s: &str| s.to_string();
    WarpPartial {
        num_views: 3,
        num_masks: 6,
        num_view_pairs: 4,
        first_pair: 1,
        counters: [0, 5, 96, 10, 6, 80, 2, 1, 0, 0],
        inputs: [
            input("4096:00000000deadbeef"),
            input("8192:0123456789abcdef"),
            input("512:1111222233334444"),
            input("none"),
            input("{\"tau_iou\":0.5}"),
        ],
        pairs: vec![[0, 2], [1, 2]].into(),
        edge_offsets: vec![0, 2, 2].into(),
        edge_masks: vec![[0, 4], [1, 5]].into(),
        edge_scores: vec![[0.75, 0.5], [0.1, 1.0]].into(),
        extra: BTreeMap::from([("generator".to_string(), "samples".to_string())]),
    }
}

/// One golden file: its path under `formats/vectors/` and its bytes.
#[derive(Debug, Clone)]
pub struct Vector {
    /// Relative path, e.g. `valid/cameras.safetensors`.
    pub name: String,
    /// File contents.
    pub bytes: Vec<u8>,
    /// For invalid files: the expected error code and field.
    pub expect_error: Option<(&'static str, Option<&'static str>)>,
}

fn unvalidated<K: FileKind>(value: &K) -> FileWriter<'_> {
    let mut w = FileWriter::new(K::KIND);
    value.fill(&mut w);
    w
}

fn bytes_of(w: &FileWriter<'_>) -> Vec<u8> {
    // Serialising in memory only fails on inconsistent shapes, which the vectors never
    // have (they are built to be checked by readers, not by the serialiser).
    w.to_bytes().unwrap_or_default()
}

/// Rewrites the JSON header of a serialised file, keeping the data section.
pub fn rewrite_header(
    bytes: &[u8],
    edit: impl FnOnce(&mut serde_json::Map<String, Value>),
) -> Vec<u8> {
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap_or([0; 8])) as usize;
    let mut header: serde_json::Map<String, Value> =
        serde_json::from_slice(&bytes[8..8 + n]).unwrap_or_default();
    edit(&mut header);
    let mut text = serde_json::to_string(&Value::Object(header))
        .unwrap_or_default()
        .into_bytes();
    while !(8 + text.len()).is_multiple_of(8) {
        text.push(b' ');
    }
    let mut out = (text.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&text);
    out.extend_from_slice(&bytes[8 + n..]);
    out
}

/// A kind's sample plus the defects that apply to it.
struct Case {
    stem: &'static str,
    valid: Vec<u8>,
    /// (case name, bytes, code, field)
    invalid: Vec<(&'static str, Vec<u8>, &'static str, Option<&'static str>)>,
}

/// Container-level defects that apply to every kind, built from its valid bytes.
fn container_defects(
    valid: &[u8],
    tensor: &'static str,
) -> Vec<(&'static str, Vec<u8>, &'static str, Option<&'static str>)> {
    let mut out = Vec::new();
    out.push((
        "truncated",
        valid[..valid.len() - 3].to_vec(),
        "truncated",
        None,
    ));
    out.push(("short", valid[..5].to_vec(), "truncated", None));
    let mut past = valid.to_vec();
    let huge = (valid.len() as u64) * 2;
    past[..8].copy_from_slice(&huge.to_le_bytes());
    out.push(("header_past_eof", past, "truncated", None));
    let mut not_json = valid.to_vec();
    not_json[8] = b'#';
    out.push(("not_json", not_json, "header", None));
    out.push((
        "lying_shape",
        rewrite_header(valid, |h| {
            if let Some(Value::Array(shape)) = h.get_mut(tensor).and_then(|t| t.get_mut("shape")) {
                shape.insert(0, json!(2));
            }
        }),
        "header",
        None,
    ));
    out.push((
        "overlap",
        rewrite_header(valid, |h| {
            if let Some(Value::Array(off)) =
                h.get_mut(tensor).and_then(|t| t.get_mut("data_offsets"))
            {
                let b = off[0].as_u64().unwrap_or(0);
                let e = off[1].as_u64().unwrap_or(0);
                if b >= 4 {
                    *off = vec![json!(b - 4), json!(e - 4)];
                } else {
                    *off = vec![json!(b + 4), json!(e + 4)];
                }
            }
        }),
        "header",
        None,
    ));
    let mut trailing = valid.to_vec();
    trailing.extend_from_slice(&[0u8; 8]);
    out.push(("trailing_bytes", trailing, "header", None));
    out.push((
        "wrong_kind",
        rewrite_header(valid, |h| set_meta(h, "format", "profuse.unknown")),
        "wrong_kind",
        Some("format"),
    ));
    out.push((
        "no_metadata",
        rewrite_header(valid, |h| {
            h.remove("__metadata__");
        }),
        "wrong_kind",
        Some("format"),
    ));
    out.push((
        "wrong_version",
        rewrite_header(valid, |h| set_meta(h, "format_version", "2.0")),
        "wrong_version",
        Some("format_version"),
    ));
    out.push((
        "bad_version",
        rewrite_header(valid, |h| set_meta(h, "format_version", "1")),
        "wrong_version",
        Some("format_version"),
    ));
    out
}

fn set_meta(h: &mut serde_json::Map<String, Value>, key: &str, value: &str) {
    if let Some(Value::Object(m)) = h.get_mut("__metadata__") {
        m.insert(key.to_string(), json!(value));
    }
}

/// Re-types a tensor's header entry to `dtype`, rewriting its bytes so the header stays
/// truthful (element values converted through f64).
fn retype(valid: &[u8], tensor: &str, dtype: Dtype) -> Vec<u8> {
    rebuild(valid, tensor, |info, raw| {
        Some((
            dtype,
            info.shape.clone(),
            encode_f64(dtype, &decode_f64(info.dtype, &raw)),
        ))
    })
}

/// Re-serialises a file with its metadata, replacing tensor `tensor` by what `edit`
/// returns for it (dtype, shape, bytes) or dropping it on `None`; other tensors are kept.
fn rebuild(
    valid: &[u8],
    tensor: &str,
    edit: impl FnOnce(&crate::container::TensorInfo, Vec<u8>) -> Option<(Dtype, Vec<usize>, Vec<u8>)>,
) -> Vec<u8> {
    let Ok(c) = Container::from_vec("rebuild", valid.to_vec()) else {
        return Vec::new();
    };
    // The kind given here is overridden by the copied `format` metadata.
    let mut w = FileWriter::new(Kind::Cameras);
    for (k, v) in c.metadata() {
        w.meta(k, v.clone());
    }
    let mut edit = Some(edit);
    for (name, info) in c.tensors() {
        let raw = c.raw(name).unwrap_or_default().to_vec();
        let replacement = match edit.take_if(|_| name == tensor) {
            Some(f) => f(info, raw),
            None => Some((info.dtype, info.shape.clone(), raw)),
        };
        if let Some((dtype, shape, bytes)) = replacement {
            w.raw_tensor(name, dtype, &shape, bytes);
        }
    }
    bytes_of(&w)
}

fn decode_f64(dtype: Dtype, raw: &[u8]) -> Vec<f64> {
    let size = dtype.size();
    raw.chunks_exact(size)
        .map(|b| match dtype {
            Dtype::U8 => f64::from(b[0]),
            Dtype::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
            Dtype::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Dtype::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Dtype::F16 => f16::from_le_bytes([b[0], b[1]]).to_f64(),
            Dtype::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Dtype::F64 => f64::from_le_bytes(b.try_into().unwrap_or([0; 8])),
            Dtype::U64 => u64::from_le_bytes(b.try_into().unwrap_or([0; 8])) as f64,
            _ => 0.0,
        })
        .collect()
}

fn encode_f64(dtype: Dtype, values: &[f64]) -> Vec<u8> {
    values
        .iter()
        .flat_map(|v| match dtype {
            Dtype::F64 => v.to_le_bytes().to_vec(),
            Dtype::F32 => (*v as f32).to_le_bytes().to_vec(),
            Dtype::I64 => (*v as i64).to_le_bytes().to_vec(),
            Dtype::I32 => (*v as i32).to_le_bytes().to_vec(),
            Dtype::U8 => vec![*v as u8],
            _ => (*v as u32).to_le_bytes().to_vec(),
        })
        .collect()
}

/// Rewrites one tensor's header shape and bytes (e.g. drops a row), keeping the rest.
fn reshape(valid: &[u8], tensor: &str, shape: &[usize]) -> Vec<u8> {
    rebuild(valid, tensor, |info, mut bytes| {
        bytes.resize(shape.iter().product::<usize>() * info.dtype.size(), 0);
        Some((info.dtype, shape.to_vec(), bytes))
    })
}

fn without_tensor(valid: &[u8], tensor: &str) -> Vec<u8> {
    rebuild(valid, tensor, |_, _| None)
}

fn mutated<K: FileKind + Clone>(value: &K, edit: impl FnOnce(&mut K)) -> Vec<u8> {
    let mut v = value.clone();
    edit(&mut v);
    bytes_of(&unvalidated(&v))
}

fn with_meta<K: FileKind>(value: &K, key: &str, val: Option<&str>) -> Vec<u8> {
    let mut w = unvalidated(value);
    match val {
        Some(v) => w.meta(key, v.to_string()),
        None => w.remove_meta(key),
    };
    bytes_of(&w)
}

fn set<T: crate::container::Element>(b: &mut crate::Buffer<T>, i: usize, v: T) {
    let mut vec = b.to_vec();
    vec[i] = v;
    *b = vec.into();
}

#[allow(clippy::too_many_lines)]
fn cases() -> Vec<Case> {
    let mut cases = Vec::new();

    let cam = cameras();
    let v = bytes_of(&unvalidated(&cam));
    let mut inv = container_defects(&v, "intrinsics");
    inv.push((
        "missing_tensor",
        without_tensor(&v, "intrinsics"),
        "missing_tensor",
        Some("intrinsics"),
    ));
    inv.push((
        "dtype",
        retype(&v, "intrinsics", Dtype::F32),
        "dtype",
        Some("intrinsics"),
    ));
    inv.push((
        "shape",
        reshape(&v, "world_to_camera", &[2, 4, 3]),
        "shape",
        Some("world_to_camera"),
    ));
    inv.push((
        "metadata",
        with_meta(&cam, "image_names", Some("images/a.png")),
        "metadata",
        Some("image_names"),
    ));
    inv.push((
        "names_count",
        with_meta(&cam, "image_names", Some("[\"a.png\"]")),
        "shape",
        Some("image_size"),
    ));
    inv.push((
        "out_of_range",
        mutated(&cam, |c| set(&mut c.image_size, 1, [8, 0])),
        "out_of_range",
        Some("image_size"),
    ));
    inv.push((
        "focal",
        mutated(&cam, |c| set(&mut c.intrinsics, 0, [-1.0, 10.0, 4.0, 3.0])),
        "out_of_range",
        Some("intrinsics"),
    ));
    inv.push((
        "non_finite",
        mutated(&cam, |c| {
            set(&mut c.intrinsics, 1, [12.0, f64::NAN, 4.5, 3.0])
        }),
        "non_finite",
        Some("intrinsics"),
    ));
    inv.push((
        "invalid",
        mutated(&cam, |c| {
            let mut m = c.world_to_camera[0];
            m[0] = 1.1;
            set(&mut c.world_to_camera, 0, m);
        }),
        "invalid",
        Some("world_to_camera"),
    ));
    inv.push((
        "reflection",
        mutated(&cam, |c| {
            let mut m = c.world_to_camera[0];
            m[10] = -1.0;
            set(&mut c.world_to_camera, 0, m);
        }),
        "invalid",
        Some("world_to_camera"),
    ));
    inv.push((
        "distortion_nan",
        mutated(&cam, |c| {
            if let Some(d) = &mut c.distortion {
                set(d, 0, [f64::INFINITY, 0.0, 0.0, 0.0]);
            }
        }),
        "non_finite",
        Some("distortion"),
    ));
    cases.push(Case {
        stem: "cameras",
        valid: v,
        invalid: inv,
    });

    let g = gaussians();
    let v = bytes_of(&unvalidated(&g));
    let mut inv = container_defects(&v, "means");
    inv.push((
        "missing_tensor",
        without_tensor(&v, "rotations"),
        "missing_tensor",
        Some("rotations"),
    ));
    inv.push((
        "missing_sh_rest",
        without_tensor(&v, "sh_rest"),
        "missing_tensor",
        Some("sh_rest"),
    ));
    inv.push((
        "dtype",
        retype(&v, "means", Dtype::F64),
        "dtype",
        Some("means"),
    ));
    inv.push((
        "shape",
        reshape(&v, "opacity_logits", &[3]),
        "shape",
        Some("opacity_logits"),
    ));
    inv.push((
        "sh_shape",
        reshape(&v, "sh_rest", &[4, 8, 3]),
        "shape",
        Some("sh_rest"),
    ));
    inv.push((
        "metadata",
        with_meta(&g, "sh_degree", Some("4")),
        "metadata",
        Some("sh_degree"),
    ));
    inv.push((
        "metadata_absent",
        with_meta(&g, "sh_degree", None),
        "metadata",
        Some("sh_degree"),
    ));
    inv.push((
        "out_of_range",
        mutated(&g, |g| {
            if let Some(c) = &mut g.class_ids {
                set(c, 2, -2)
            }
        }),
        "out_of_range",
        Some("class_ids"),
    ));
    inv.push((
        "non_finite",
        mutated(&g, |g| set(&mut g.opacity_logits, 3, f32::INFINITY)),
        "non_finite",
        Some("opacity_logits"),
    ));
    inv.push((
        "means_nan",
        mutated(&g, |g| set(&mut g.means, 1, [0.0, f32::NAN, 0.0])),
        "non_finite",
        Some("means"),
    ));
    inv.push((
        "invalid",
        mutated(&g, |g| set(&mut g.rotations, 2, [0.0; 4])),
        "invalid",
        Some("rotations"),
    ));
    cases.push(Case {
        stem: "gaussians",
        valid: v,
        invalid: inv,
    });

    let m = masks();
    let v = bytes_of(&unvalidated(&m));
    let mut inv = container_defects(&v, "labels");
    inv.push((
        "missing_tensor",
        without_tensor(&v, "mask_offsets"),
        "missing_tensor",
        Some("mask_offsets"),
    ));
    inv.push((
        "dtype",
        retype(&v, "labels", Dtype::I32),
        "dtype",
        Some("labels"),
    ));
    inv.push((
        "shape",
        reshape(&v, "mask_offsets", &[2]),
        "shape",
        Some("mask_offsets"),
    ));
    inv.push((
        "metadata",
        with_meta(&m, "view_names", None),
        "metadata",
        Some("view_names"),
    ));
    inv.push((
        "out_of_range",
        mutated(&m, |m| {
            if let Labels::U16(b) = &mut m.labels {
                set(b, 13, 2)
            }
        }),
        "out_of_range",
        Some("labels"),
    ));
    inv.push((
        "offsets",
        mutated(&m, |m| m.mask_offsets = vec![0, 4, 3].into()),
        "out_of_range",
        Some("mask_offsets"),
    ));
    inv.push((
        "non_finite",
        mutated(&m, |m| {
            if let Floats::F16(b) = &mut m.features {
                set(b, 5, f16::NAN)
            }
        }),
        "non_finite",
        Some("features"),
    ));
    inv.push((
        "invalid",
        mutated(&m, |m| {
            if let Floats::F16(b) = &mut m.features {
                set(b, 0, f16::from_f32(0.5))
            }
        }),
        "invalid",
        Some("features"),
    ));
    cases.push(Case {
        stem: "masks",
        valid: v,
        invalid: inv,
    });
    cases.push(Case {
        stem: "masks_wide",
        valid: bytes_of(&unvalidated(&masks_wide())),
        invalid: Vec::new(),
    });

    let mt = matches();
    let v = bytes_of(&unvalidated(&mt));
    let mut inv = container_defects(&v, "warp");
    inv.push((
        "missing_tensor",
        without_tensor(&v, "certainty"),
        "missing_tensor",
        Some("certainty"),
    ));
    inv.push((
        "dtype",
        retype(&v, "warp", Dtype::F64),
        "dtype",
        Some("warp"),
    ));
    inv.push((
        "shape",
        reshape(&v, "certainty", &[2, 3, 2]),
        "shape",
        Some("certainty"),
    ));
    inv.push((
        "metadata",
        with_meta(&mt, "coords", Some("meters")),
        "metadata",
        Some("coords"),
    ));
    inv.push((
        "out_of_range",
        mutated(&mt, |m| set(&mut m.pairs, 1, [1, 2])),
        "out_of_range",
        Some("pairs"),
    ));
    inv.push((
        "certainty_range",
        mutated(&mt, |m| {
            if let Floats::F32(b) = &mut m.certainty {
                set(b, 4, 1.5)
            }
        }),
        "out_of_range",
        Some("certainty"),
    ));
    inv.push((
        "non_finite",
        mutated(&mt, |m| {
            if let Floats::F32(b) = &mut m.warp {
                set(b, 7, f32::NAN)
            }
        }),
        "non_finite",
        Some("warp"),
    ));
    inv.push((
        "invalid",
        mutated(&mt, |m| set(&mut m.pairs, 1, [0, 1])),
        "invalid",
        Some("pairs"),
    ));
    cases.push(Case {
        stem: "matches",
        valid: v,
        invalid: inv,
    });
    cases.push(Case {
        stem: "matches_half",
        valid: bytes_of(&unvalidated(&matches_half())),
        invalid: Vec::new(),
    });

    let sm = sparse_matches();
    let v = bytes_of(&unvalidated(&sm));
    let mut inv = container_defects(&v, "points_i");
    inv.push((
        "missing_tensor",
        without_tensor(&v, "pair_offsets"),
        "missing_tensor",
        Some("pair_offsets"),
    ));
    inv.push((
        "dtype",
        retype(&v, "pair_offsets", Dtype::U32),
        "dtype",
        Some("pair_offsets"),
    ));
    inv.push((
        "shape",
        reshape(&v, "points_j", &[4, 2]),
        "shape",
        Some("points_j"),
    ));
    inv.push((
        "metadata",
        with_meta(&sm, "num_views", Some("three")),
        "metadata",
        Some("num_views"),
    ));
    inv.push((
        "out_of_range",
        mutated(&sm, |m| m.pair_offsets = vec![0, 4, 3].into()),
        "out_of_range",
        Some("pair_offsets"),
    ));
    inv.push((
        "non_finite",
        mutated(&sm, |m| set(&mut m.points_j, 2, [f32::INFINITY, 0.0])),
        "non_finite",
        Some("points_j"),
    ));
    inv.push((
        "invalid",
        mutated(&sm, |m| set(&mut m.pairs, 1, [2, 2])),
        "invalid",
        Some("pairs"),
    ));
    cases.push(Case {
        stem: "sparse_matches",
        valid: v,
        invalid: inv,
    });

    let p = proposals();
    let v = bytes_of(&unvalidated(&p));
    let mut inv = container_defects(&v, "mask_proposal");
    inv.push((
        "missing_tensor",
        without_tensor(&v, "proposal_views"),
        "missing_tensor",
        Some("proposal_views"),
    ));
    inv.push((
        "dtype",
        retype(&v, "mask_proposal", Dtype::I64),
        "dtype",
        Some("mask_proposal"),
    ));
    inv.push((
        "shape",
        reshape(&v, "proposal_views", &[3]),
        "shape",
        Some("proposal_views"),
    ));
    inv.push((
        "out_of_range",
        mutated(&p, |p| set(&mut p.mask_proposal, 2, 2)),
        "out_of_range",
        Some("mask_proposal"),
    ));
    inv.push((
        "views",
        mutated(&p, |p| set(&mut p.proposal_views, 0, 3)),
        "out_of_range",
        Some("proposal_views"),
    ));
    inv.push((
        "invalid",
        mutated(&p, |p| set(&mut p.proposal_size, 1, 3)),
        "invalid",
        Some("proposal_size"),
    ));
    inv.push((
        "share",
        mutated(&p, |p| {
            if let Some(s) = p.mask_share.as_mut() {
                set(s, 1, 1.5);
            }
        }),
        "out_of_range",
        Some("mask_share"),
    ));
    inv.push((
        "instance",
        mutated(&p, |p| {
            if let Some(i) = p.mask_instance.as_mut() {
                set(i, 1, 0);
            }
        }),
        "invalid",
        Some("mask_instance"),
    ));
    cases.push(Case {
        stem: "proposals",
        valid: v,
        invalid: inv,
    });

    let f = features();
    let v = bytes_of(&unvalidated(&f));
    let mut inv = container_defects(&v, "features");
    inv.push((
        "missing_tensor",
        without_tensor(&v, "valid"),
        "missing_tensor",
        Some("valid"),
    ));
    inv.push((
        "dtype",
        retype(&v, "valid", Dtype::I32),
        "dtype",
        Some("valid"),
    ));
    inv.push(("shape", reshape(&v, "valid", &[3]), "shape", Some("valid")));
    inv.push((
        "out_of_range",
        mutated(&f, |f| set(&mut f.valid, 0, 2)),
        "out_of_range",
        Some("valid"),
    ));
    inv.push((
        "non_finite",
        mutated(&f, |f| {
            if let Floats::F32(b) = &mut f.features {
                set(b, 1, f32::NAN)
            }
        }),
        "non_finite",
        Some("features"),
    ));
    inv.push((
        "invalid",
        mutated(&f, |f| {
            if let Floats::F32(b) = &mut f.features {
                set(b, 9, 0.25)
            }
        }),
        "invalid",
        Some("features"),
    ));
    inv.push((
        "weight_sum",
        mutated(&f, |f| {
            if let Some(s) = &mut f.weight_sum {
                set(s, 2, 1.0)
            }
        }),
        "invalid",
        Some("weight_sum"),
    ));
    cases.push(Case {
        stem: "features",
        valid: v,
        invalid: inv,
    });

    let q = pq();
    let v = bytes_of(&unvalidated(&q));
    let mut inv = container_defects(&v, "centroids");
    inv.push((
        "missing_tensor",
        without_tensor(&v, "codes"),
        "missing_tensor",
        Some("codes"),
    ));
    inv.push((
        "dtype",
        retype(&v, "centroids", Dtype::F64),
        "dtype",
        Some("centroids"),
    ));
    inv.push((
        "shape",
        reshape(&v, "centroids", &[2, 128, 2]),
        "shape",
        Some("centroids"),
    ));
    inv.push((
        "metadata",
        with_meta(&q, "metric", Some("l2")),
        "metadata",
        Some("metric"),
    ));
    inv.push((
        "out_of_range",
        mutated(&q, |q| set(&mut q.valid, 1, 7)),
        "out_of_range",
        Some("valid"),
    ));
    inv.push((
        "non_finite",
        mutated(&q, |q| set(&mut q.centroids, 100, f32::NEG_INFINITY)),
        "non_finite",
        Some("centroids"),
    ));
    inv.push((
        "invalid",
        mutated(&q, |q| set(&mut q.norms, 2, 0.5)),
        "invalid",
        Some("norms"),
    ));
    cases.push(Case {
        stem: "pq",
        valid: v,
        invalid: inv,
    });

    let pr = prompts();
    let v = bytes_of(&unvalidated(&pr));
    let mut inv = container_defects(&v, "embeddings");
    inv.push((
        "missing_tensor",
        without_tensor(&v, "embeddings"),
        "missing_tensor",
        Some("embeddings"),
    ));
    inv.push((
        "dtype",
        retype(&v, "embeddings", Dtype::F64),
        "dtype",
        Some("embeddings"),
    ));
    inv.push((
        "shape",
        reshape(&v, "class_ids", &[2]),
        "shape",
        Some("class_ids"),
    ));
    inv.push((
        "metadata",
        with_meta(&pr, "names", Some("[\"chair\",\"chair\",\"object\"]")),
        "metadata",
        Some("names"),
    ));
    inv.push((
        "out_of_range",
        mutated(&pr, |p| {
            if let Some(c) = &mut p.class_ids {
                set(c, 0, -5)
            }
        }),
        "out_of_range",
        Some("class_ids"),
    ));
    inv.push((
        "non_finite",
        mutated(&pr, |p| set(&mut p.embeddings, 6, f32::NAN)),
        "non_finite",
        Some("embeddings"),
    ));
    inv.push((
        "invalid",
        mutated(&pr, |p| {
            let mut e = p.embeddings.to_vec();
            e[4..8].fill(0.0);
            p.embeddings = e.into();
        }),
        "invalid",
        Some("embeddings"),
    ));
    cases.push(Case {
        stem: "prompts",
        valid: v,
        invalid: inv,
    });

    let s = selection();
    let v = bytes_of(&unvalidated(&s));
    let mut inv = container_defects(&v, "scores");
    inv.push((
        "missing_tensor",
        without_tensor(&v, "scores"),
        "missing_tensor",
        Some("scores"),
    ));
    inv.push((
        "dtype",
        retype(&v, "gaussian_ids", Dtype::I64),
        "dtype",
        Some("gaussian_ids"),
    ));
    inv.push((
        "shape",
        reshape(&v, "scores", &[2]),
        "shape",
        Some("scores"),
    ));
    inv.push((
        "metadata",
        with_meta(&s, "num_gaussians", Some("-3")),
        "metadata",
        Some("num_gaussians"),
    ));
    inv.push((
        "out_of_range",
        mutated(&s, |s| set(&mut s.gaussian_ids, 2, 10)),
        "out_of_range",
        Some("gaussian_ids"),
    ));
    inv.push((
        "unsorted",
        mutated(&s, |s| set(&mut s.gaussian_ids, 1, 1)),
        "out_of_range",
        Some("gaussian_ids"),
    ));
    inv.push((
        "non_finite",
        mutated(&s, |s| set(&mut s.scores, 0, f32::NAN)),
        "non_finite",
        Some("scores"),
    ));
    cases.push(Case {
        stem: "selection",
        valid: v,
        invalid: inv,
    });

    let vl = vertex_labels();
    let v = bytes_of(&unvalidated(&vl));
    let mut inv = container_defects(&v, "labels");
    inv.push((
        "missing_tensor",
        without_tensor(&v, "labels"),
        "missing_tensor",
        Some("labels"),
    ));
    inv.push((
        "dtype",
        retype(&v, "labels", Dtype::U32),
        "dtype",
        Some("labels"),
    ));
    inv.push((
        "shape",
        reshape(&v, "confidence", &[4]),
        "shape",
        Some("confidence"),
    ));
    inv.push((
        "out_of_range",
        mutated(&vl, |v| set(&mut v.labels, 3, -7)),
        "out_of_range",
        Some("labels"),
    ));
    inv.push((
        "confidence_range",
        mutated(&vl, |v| {
            if let Some(c) = &mut v.confidence {
                set(c, 1, 1.5)
            }
        }),
        "out_of_range",
        Some("confidence"),
    ));
    inv.push((
        "non_finite",
        mutated(&vl, |v| {
            if let Some(c) = &mut v.confidence {
                set(c, 1, f32::NAN)
            }
        }),
        "non_finite",
        Some("confidence"),
    ));
    cases.push(Case {
        stem: "vertex_labels",
        valid: v,
        invalid: inv,
    });

    let me = mesh();
    let v = bytes_of(&unvalidated(&me));
    let mut inv = container_defects(&v, "vertices");
    inv.push((
        "missing_tensor",
        without_tensor(&v, "vertices"),
        "missing_tensor",
        Some("vertices"),
    ));
    inv.push((
        "dtype",
        retype(&v, "faces", Dtype::I64),
        "dtype",
        Some("faces"),
    ));
    inv.push((
        "shape",
        reshape(&v, "labels", &[3]),
        "shape",
        Some("labels"),
    ));
    inv.push((
        "out_of_range",
        mutated(&me, |m| {
            if let Some(f) = &mut m.faces {
                set(f, 1, [0, 2, 4])
            }
        }),
        "out_of_range",
        Some("faces"),
    ));
    inv.push((
        "non_finite",
        mutated(&me, |m| set(&mut m.vertices, 3, [0.0, f32::NAN, 0.0])),
        "non_finite",
        Some("vertices"),
    ));
    cases.push(Case {
        stem: "mesh",
        valid: v,
        invalid: inv,
    });

    let vm = view_maps();
    let v = bytes_of(&unvalidated(&vm));
    let mut inv = container_defects(&v, "depth");
    inv.push((
        "missing_tensor",
        without_tensor(&v, "depth"),
        "missing_tensor",
        Some("depth"),
    ));
    inv.push((
        "dtype",
        retype(&v, "depth", Dtype::F64),
        "dtype",
        Some("depth"),
    ));
    inv.push((
        "shape",
        reshape(&v, "object_ids", &[2, 3, 2]),
        "shape",
        Some("object_ids"),
    ));
    inv.push((
        "metadata",
        with_meta(&vm, "num_objects", None),
        "metadata",
        Some("num_objects"),
    ));
    inv.push((
        "out_of_range",
        mutated(&vm, |m| {
            if let Some(o) = &mut m.object_ids {
                set(o, 4, 3)
            }
        }),
        "out_of_range",
        Some("object_ids"),
    ));
    inv.push((
        "negative_depth",
        mutated(&vm, |m| set(&mut m.depth, 2, -1.0)),
        "out_of_range",
        Some("depth"),
    ));
    inv.push((
        "non_finite",
        mutated(&vm, |m| set(&mut m.depth, 5, f32::INFINITY)),
        "non_finite",
        Some("depth"),
    ));
    cases.push(Case {
        stem: "view_maps",
        valid: v,
        invalid: inv,
    });

    let tk = topk();
    let v = bytes_of(&unvalidated(&tk));
    let mut inv = container_defects(&v, "weights");
    inv.push((
        "missing_tensor",
        without_tensor(&v, "transmittance"),
        "missing_tensor",
        Some("transmittance"),
    ));
    inv.push((
        "dtype",
        retype(&v, "weights", Dtype::F64),
        "dtype",
        Some("weights"),
    ));
    inv.push((
        "shape",
        reshape(&v, "weights", &[2, 3, 2]),
        "shape",
        Some("weights"),
    ));
    inv.push((
        "metadata",
        with_meta(&tk, "num_gaussians", None),
        "metadata",
        Some("num_gaussians"),
    ));
    inv.push((
        "out_of_range",
        mutated(&tk, |t| set(&mut t.ids, 1, 7)),
        "out_of_range",
        Some("ids"),
    ));
    inv.push((
        "weight_range",
        mutated(&tk, |t| set(&mut t.weights, 0, 1.5)),
        "out_of_range",
        Some("weights"),
    ));
    inv.push((
        "non_finite",
        mutated(&tk, |t| set(&mut t.weights, 4, f32::NAN)),
        "non_finite",
        Some("weights"),
    ));
    inv.push((
        "padding",
        mutated(&tk, |t| set(&mut t.weights, 4, 0.05)),
        "invalid",
        Some("weights"),
    ));
    inv.push((
        "unsorted",
        mutated(&tk, |t| set(&mut t.weights, 1, 0.6)),
        "invalid",
        Some("weights"),
    ));
    inv.push((
        "sum",
        mutated(&tk, |t| set(&mut t.transmittance, 0, 0.5)),
        "invalid",
        Some("weights"),
    ));
    inv.push((
        "transmittance",
        mutated(&tk, |t| set(&mut t.transmittance, 2, -0.5)),
        "out_of_range",
        Some("transmittance"),
    ));
    cases.push(Case {
        stem: "topk",
        valid: v,
        invalid: inv,
    });
    cases.push(fuse_partial_case());
    cases.push(warp_partial_case());
    cases.push(semantic_index_case());

    cases
}

/// The fuse_partial sample and its defects.
fn fuse_partial_case() -> Case {
    let fp = fuse_partial();
    let v = bytes_of(&unvalidated(&fp));
    let mut inv = container_defects(&v, "w_sums");
    let proposals = |p: &mut FusePartial| {
        p.grouping = FuseGrouping::Proposals {
            orphans: FuseOrphans::Ignore,
        };
    };
    inv.extend([
        (
            "missing_tensor",
            without_tensor(&v, "w_offsets"),
            "missing_tensor",
            Some("w_offsets"),
        ),
        (
            "missing_proposal",
            without_tensor(&v, "mask_proposal"),
            "missing_tensor",
            Some("mask_proposal"),
        ),
        (
            "dtype",
            retype(&v, "mask_mass", Dtype::F64),
            "dtype",
            Some("mask_mass"),
        ),
        (
            "shape",
            reshape(&v, "w_sums", &[4, 3]),
            "shape",
            Some("w_sums"),
        ),
        (
            "offsets_shape",
            reshape(&v, "w_offsets", &[4]),
            "shape",
            Some("w_offsets"),
        ),
        (
            "metadata",
            with_meta(&fp, "num_groups", None),
            "metadata",
            Some("num_groups"),
        ),
        (
            "grouping",
            with_meta(&fp, "grouping", Some("kmeans")),
            "metadata",
            Some("grouping"),
        ),
        (
            "orphans",
            with_meta(&fp, "orphans", Some("none")),
            "metadata",
            Some("orphans"),
        ),
        (
            "blend_groups",
            with_meta(&fp, "num_groups", Some("4")),
            "metadata",
            Some("num_groups"),
        ),
        (
            "views",
            mutated(&fp, |p| set(&mut p.views, 1, 0)),
            "out_of_range",
            Some("views"),
        ),
        (
            "out_of_range",
            mutated(&fp, |p| set(&mut p.mask_group, 2, 3)),
            "out_of_range",
            Some("mask_group"),
        ),
        (
            "invalid",
            mutated(&fp, |p| {
                if let Some(mp) = &mut p.mask_proposal {
                    set(mp, 1, 0);
                }
            }),
            "invalid",
            Some("mask_group"),
        ),
        (
            "stray_proposal",
            mutated(&fp, proposals),
            "invalid",
            Some("mask_proposal"),
        ),
        (
            "masks_groups",
            mutated(&fp, |p| {
                p.grouping = FuseGrouping::Masks;
                p.mask_proposal = None;
            }),
            "invalid",
            Some("mask_group"),
        ),
        (
            "non_finite",
            mutated(&fp, |p| {
                p.mask_features = vec![1.0, 0.0, f32::NAN, 0.8, 0.0, 1.0].into()
            }),
            "non_finite",
            Some("mask_features"),
        ),
        (
            "offsets",
            mutated(&fp, |p| set(&mut p.w_offsets, 2, 1)),
            "out_of_range",
            Some("w_offsets"),
        ),
        (
            "unsorted",
            mutated(&fp, |p| set(&mut p.w_groups, 1, 0)),
            "out_of_range",
            Some("w_groups"),
        ),
        (
            "zero_sum",
            mutated(&fp, |p| set(&mut p.w_sums, 2, [0, 0])),
            "out_of_range",
            Some("w_sums"),
        ),
        (
            "share",
            mutated(&fp, |p| {
                if let Some(s) = p.mask_share.as_mut() {
                    set(s, 0, 0.0);
                }
            }),
            "out_of_range",
            Some("mask_share"),
        ),
    ]);
    Case {
        stem: "fuse_partial",
        valid: v,
        invalid: inv,
    }
}

/// The warp_partial sample and its defects.
fn warp_partial_case() -> Case {
    let wp = warp_partial();
    let v = bytes_of(&unvalidated(&wp));
    let mut inv = container_defects(&v, "edge_scores");
    inv.extend([
        (
            "missing_tensor",
            without_tensor(&v, "edge_offsets"),
            "missing_tensor",
            Some("edge_offsets"),
        ),
        (
            "dtype",
            retype(&v, "edge_scores", Dtype::F32),
            "dtype",
            Some("edge_scores"),
        ),
        (
            "shape",
            reshape(&v, "edge_scores", &[3, 2]),
            "shape",
            Some("edge_scores"),
        ),
        (
            "offsets_shape",
            reshape(&v, "edge_offsets", &[4]),
            "shape",
            Some("edge_offsets"),
        ),
        (
            "metadata",
            with_meta(&wp, "cells_gated", Some("-1")),
            "metadata",
            Some("cells_gated"),
        ),
        (
            "no_input",
            with_meta(&wp, "input_matches", None),
            "metadata",
            Some("input_matches"),
        ),
        (
            "past_end",
            with_meta(&wp, "first_pair", Some("3")),
            "metadata",
            Some("first_pair"),
        ),
        (
            "pairs",
            mutated(&wp, |p| set(&mut p.pairs, 1, [2, 1])),
            "out_of_range",
            Some("pairs"),
        ),
        (
            "unsorted",
            mutated(&wp, |p| set(&mut p.pairs, 1, [0, 1])),
            "out_of_range",
            Some("pairs"),
        ),
        (
            "offsets",
            mutated(&wp, |p| set(&mut p.edge_offsets, 2, 1)),
            "out_of_range",
            Some("edge_offsets"),
        ),
        (
            "out_of_range",
            mutated(&wp, |p| set(&mut p.edge_masks, 1, [1, 6])),
            "out_of_range",
            Some("edge_masks"),
        ),
        (
            "non_finite",
            mutated(&wp, |p| set(&mut p.edge_scores, 0, [f64::NAN, 0.5])),
            "non_finite",
            Some("edge_scores"),
        ),
        (
            "score",
            mutated(&wp, |p| set(&mut p.edge_scores, 1, [0.1, 1.5])),
            "out_of_range",
            Some("edge_scores"),
        ),
    ]);
    Case {
        stem: "warp_partial",
        valid: v,
        invalid: inv,
    }
}

/// Every golden vector, valid files first.
pub fn vectors() -> Vec<Vector> {
    let mut out = Vec::new();
    let cases = cases();
    for c in &cases {
        out.push(Vector {
            name: format!("valid/{}.safetensors", c.stem),
            bytes: c.valid.clone(),
            expect_error: None,
        });
    }
    for c in cases {
        for (case, bytes, code, field) in c.invalid {
            out.push(Vector {
                name: format!("invalid/{}__{case}.safetensors", c.stem),
                bytes,
                expect_error: Some((code, field)),
            });
        }
    }
    out
}

/// `expected.json`: for valid vectors their kind, counts, metadata and every tensor's
/// dtype, shape and values; for invalid ones the error code and field.
pub fn expected_json(vectors: &[Vector]) -> Value {
    let mut valid = serde_json::Map::new();
    let mut invalid = serde_json::Map::new();
    for v in vectors {
        match v.expect_error {
            Some((code, field)) => {
                invalid.insert(v.name.clone(), json!({"code": code, "field": field}));
            }
            None => {
                let entry = Container::from_vec(v.name.clone(), v.bytes.clone())
                    .map(|c| describe_valid(&c))
                    .unwrap_or(Value::Null);
                valid.insert(v.name.clone(), entry);
            }
        }
    }
    json!({"valid": valid, "invalid": invalid})
}

fn describe_valid(c: &Container) -> Value {
    let counts = crate::inspect::validate_any(c).unwrap_or_default();
    let kind = c
        .metadata()
        .get("format")
        .and_then(|f| Kind::from_format_name(f))
        .map(Kind::name);
    let tensors: serde_json::Map<String, Value> = c
        .tensors()
        .iter()
        .map(|(n, t)| {
            let values = decode_values(t.dtype, c.raw(n).unwrap_or_default());
            (
                n.clone(),
                json!({"dtype": t.dtype.name(), "shape": t.shape, "values": values}),
            )
        })
        .collect();
    json!({"kind": kind, "counts": counts, "metadata": c.metadata(), "tensors": tensors})
}

fn decode_values(dtype: Dtype, raw: &[u8]) -> Vec<Value> {
    match dtype {
        Dtype::U8 => raw.iter().map(|b| json!(b)).collect(),
        Dtype::U64 => raw
            .chunks_exact(8)
            .map(|b| json!(u64::from_le_bytes(b.try_into().unwrap_or([0; 8]))))
            .collect(),
        Dtype::U16 | Dtype::U32 | Dtype::I32 => decode_f64(dtype, raw)
            .into_iter()
            .map(|v| json!(v as i64))
            .collect(),
        _ => decode_f64(dtype, raw)
            .into_iter()
            .map(|v| json!(v))
            .collect(),
    }
}
