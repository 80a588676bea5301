//! Issue 20 item 1: values from a header never size an allocation or a loop beyond what
//! the data backs. Crafted ~200-byte files with zero rows and a huge dimension (D = 2^62,
//! 2^40, 2^32, ...) made every reader panic ("capacity overflow"), abort (a multi-TB
//! allocation) or silently reserve 16 GB, because a row buffer was sized from D.
//!
//! SPEC.md §2 allows a dimension of 0 and multiplies the dimensions left to right in u64
//! (step 7), so `[0, 2^62]` is a valid zero-element tensor, and the kinds only ask D >= 1:
//! these files are **valid** and must be accepted, with the header's D reported, without
//! allocating anything sized by D. This test binary counts the largest single allocation
//! of the reading thread to prove it.
#![allow(clippy::unwrap_used, clippy::expect_used)]
// A counting global allocator needs `unsafe impl GlobalAlloc`; it only forwards to the
// system allocator.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use profuse_formats::{
    inspect, validate_any, Container, Features, FileKind, Floats, Labels, Masks, TopK,
};

struct Counting;

thread_local! {
    static LARGEST: Cell<usize> = const { Cell::new(0) };
}

// SAFETY: forwards every call to `System` unchanged; only records the size.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let _ = LARGEST.try_with(|l| l.set(l.get().max(layout.size())));
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let _ = LARGEST.try_with(|l| l.set(l.get().max(layout.size())));
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let _ = LARGEST.try_with(|l| l.set(l.get().max(new_size)));
        // SAFETY: same contract as the caller's.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: same contract as the caller's.
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Runs `f` and returns its value with the largest single allocation it made (this thread).
fn largest_allocation<T>(f: impl FnOnce() -> T) -> (T, usize) {
    LARGEST.with(|l| l.set(0));
    let value = f();
    (value, LARGEST.with(Cell::get))
}

/// No allocation while reading a ~200-byte file may exceed this.
const SMALL: usize = 64 * 1024;

/// A safetensors file from metadata and (name, dtype, shape, bytes) entries, tensors laid
/// out in the given order.
fn file(meta: &[(&str, &str)], tensors: &[(&str, &str, &[u64], &[u8])]) -> Vec<u8> {
    let mut header = serde_json::Map::new();
    let meta: serde_json::Map<String, serde_json::Value> = meta
        .iter()
        .map(|(k, v)| ((*k).to_string(), serde_json::Value::from(*v)))
        .collect();
    header.insert("__metadata__".into(), meta.into());
    let mut data = Vec::new();
    for (name, dtype, shape, bytes) in tensors {
        let begin = data.len();
        data.extend_from_slice(bytes);
        header.insert(
            (*name).to_string(),
            serde_json::json!({"dtype": dtype, "shape": shape, "data_offsets": [begin, data.len()]}),
        );
    }
    let mut text = serde_json::to_vec(&serde_json::Value::Object(header)).unwrap();
    while !(8 + text.len()).is_multiple_of(8) {
        text.push(b' ');
    }
    let mut out = (text.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&text);
    out.extend_from_slice(&data);
    out
}

fn container(bytes: Vec<u8>) -> Container {
    assert!(
        bytes.len() < 400,
        "crafted files stay small: {}",
        bytes.len()
    );
    Container::from_vec("crafted.safetensors", bytes).unwrap()
}

/// A metadata pair and a tensor entry without data (name, dtype, shape).
type Meta = (&'static str, &'static str);
type Entry = (&'static str, &'static str, Vec<u64>);

const HUGE: [u64; 6] = [1 << 32, 1 << 40, 1 << 61, 1 << 62, 1 << 63, u64::MAX];

/// Issue 20 item 1: features with zero rows and D = 2^32 .. 2^64 - 1 are valid (SPEC.md
/// §2 step 7, §4.7 D >= 1), read without any allocation sized by D, and report D.
#[test]
fn features_with_zero_rows_and_a_huge_dimension_read_without_allocating() {
    for d in HUGE {
        for dtype in ["F16", "F32"] {
            let c = container(file(
                &[("format", "profuse.features"), ("format_version", "1.0")],
                &[
                    ("features", dtype, &[0, d], b""),
                    ("valid", "U8", &[0], b""),
                ],
            ));
            let (f, largest) = largest_allocation(|| Features::from_checked_container(&c));
            let f = f.unwrap_or_else(|e| panic!("D = {d} {dtype}: {e}"));
            assert_eq!((f.len(), f.dim as u64), (0, d));
            assert!(largest < SMALL, "D = {d}: allocated {largest} bytes");
            assert_eq!(f.counts()["feature_dim"], d);
        }
    }
}

/// Issue 20 item 1: masks with zero masks and a huge D, and with zero views and a
/// `H x W` plane that overflows u64, are valid and read without allocating.
#[test]
fn masks_with_zero_masks_or_views_and_huge_dimensions_read_without_allocating() {
    let meta = [
        ("format", "profuse.masks"),
        ("format_version", "1.0"),
        ("view_names", "[]"),
    ];
    for d in HUGE {
        let c = container(file(
            &meta,
            &[
                ("mask_offsets", "U32", &[1], &[0; 4]),
                ("labels", "U16", &[0, 4, 4], b""),
                ("features", "F32", &[0, d], b""),
            ],
        ));
        let (m, largest) = largest_allocation(|| Masks::from_checked_container(&c));
        let m = m.unwrap_or_else(|e| panic!("D = {d}: {e}"));
        assert_eq!((m.num_masks(), m.dim as u64), (0, d));
        assert!(largest < SMALL, "D = {d}: allocated {largest} bytes");
    }
    // H x W = 2^80: the old reader computed the plane size up front and overflowed.
    let c = container(file(
        &meta,
        &[
            ("mask_offsets", "U32", &[1], &[0; 4]),
            ("labels", "U32", &[0, 1 << 40, 1 << 40], b""),
            ("features", "F16", &[0, 512], b""),
        ],
    ));
    let (m, largest) = largest_allocation(|| Masks::from_checked_container(&c));
    let m = m.unwrap();
    assert_eq!((m.height, m.width, m.num_views()), (1 << 40, 1 << 40, 0));
    assert!(largest < SMALL, "allocated {largest} bytes");
}

/// Issue 20 items 1 and 2: a topk file with no pixels and K = 2^31 (and K = 2^62) is
/// valid and costs nothing: no allocation or loop is sized by K.
#[test]
fn topk_with_no_pixels_and_a_huge_k_reads_without_allocating() {
    for (h, w, k) in [(0, 0, 1 << 31), (1, 0, 1 << 31), (0, 7, 1 << 62)] {
        let c = container(file(
            &[
                ("format", "profuse.topk"),
                ("format_version", "1.0"),
                ("num_gaussians", "0"),
            ],
            &[
                ("ids", "U32", &[h, w, k], b""),
                ("weights", "F32", &[h, w, k], b""),
                ("transmittance", "F32", &[h, w], b""),
            ],
        ));
        let (t, largest) = largest_allocation(|| TopK::from_checked_container(&c));
        let t = t.unwrap_or_else(|e| panic!("{h}x{w}x{k}: {e}"));
        assert_eq!(
            (t.height as u64, t.width as u64, t.k as u64),
            (h, w, k),
            "{h}x{w}x{k}"
        );
        assert!(largest < SMALL, "{h}x{w}x{k}: allocated {largest} bytes");
    }
}

/// Issue 20 item 1, the other kinds with a feature-like or plane dimension: prompts with
/// no names, pq with no vectors, matches with no pairs and view maps with no views, each
/// with huge dimensions, are valid and read without allocating.
#[test]
fn other_kinds_with_zero_rows_and_huge_dimensions_read_without_allocating() {
    let base = |kind: &'static str| vec![("format", kind), ("format_version", "1.0")];
    let mut prompts = base("profuse.prompts");
    prompts.push(("names", "[]"));
    let mut pq = base("profuse.pq");
    pq.extend([("metric", "inner_product"), ("nbits", "8")]);
    let mut matches = base("profuse.matches");
    matches.extend([("num_views", "2"), ("coords", "normalized")]);
    let mut maps = base("profuse.view_maps");
    maps.extend([("view_names", "[]"), ("num_objects", "0")]);
    let big = 1u64 << 40;
    let cases: Vec<(Vec<Meta>, Vec<Entry>)> = vec![
        (prompts, vec![("embeddings", "F32", vec![0, 1 << 62])]),
        (
            pq,
            vec![
                ("centroids", "F32", vec![0, 256, big]),
                ("codes", "U8", vec![0, 0]),
                ("norms", "F32", vec![0]),
                ("valid", "U8", vec![0]),
            ],
        ),
        (
            matches,
            vec![
                ("pairs", "U32", vec![0, 2]),
                ("warp", "F16", vec![0, big, big, 2]),
                ("certainty", "F16", vec![0, big, big]),
            ],
        ),
        (
            maps,
            vec![
                ("depth", "F32", vec![0, big, big]),
                ("object_ids", "U32", vec![0, big, big]),
            ],
        ),
    ];
    for (meta, tensors) in cases {
        let tensors: Vec<(&str, &str, &[u64], &[u8])> = tensors
            .iter()
            .map(|(n, d, s)| (*n, *d, s.as_slice(), &b""[..]))
            .collect();
        let c = container(file(&meta, &tensors));
        let kind = meta[0].1;
        let (report, largest) = largest_allocation(|| validate_any(&c));
        match kind {
            // pq with M = 0 is a shape error (M >= 1); everything else is valid.
            "profuse.pq" => assert_eq!(report.unwrap_err().code(), "shape"),
            _ => {
                report.unwrap_or_else(|e| panic!("{kind}: {e}"));
            }
        }
        assert!(largest < SMALL, "{kind}: allocated {largest} bytes");
    }
}

/// Issue 20 item 1, the write path: values whose dimensions multiply past 2^64 are a
/// `shape` error from validation, never an overflow panic or a wrapped product.
#[test]
fn writers_reject_dimensions_whose_product_overflows() {
    let masks = Masks {
        view_names: vec!["a.png".into()],
        width: 1 << 40,
        height: 1 << 40,
        labels: Labels::U16(Vec::new().into()),
        mask_offsets: vec![0, 0].into(),
        features: Floats::F32(Vec::new().into()),
        dim: 4,
        extra: Default::default(),
    };
    let err = masks.to_bytes().unwrap_err();
    assert_eq!((err.code(), err.field()), ("shape", Some("labels")));
    assert!(err.to_string().contains("overflows"), "{err}");

    let topk = TopK {
        width: 1 << 33,
        height: 1 << 33,
        k: 1,
        ..Default::default()
    };
    let err = topk.to_bytes().unwrap_err();
    assert_eq!((err.code(), err.field()), ("shape", Some("ids")));

    // Zero rows with a huge D is valid on the write path too, and written without a
    // buffer sized by D.
    let features = Features {
        features: Floats::F32(Vec::new().into()),
        dim: 1 << 62,
        valid: Vec::new().into(),
        weight_sum: None,
        extra: Default::default(),
    };
    let (bytes, largest) = largest_allocation(|| features.to_bytes());
    let back = Features::from_checked_container(&container(bytes.unwrap())).unwrap();
    assert_eq!(back.dim, 1 << 62);
    assert!(largest < SMALL, "allocated {largest} bytes");
}

/// The `inspect` report of such a file is valid and shows the header's shape.
#[test]
fn inspect_reports_the_huge_dimension() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("features.safetensors");
    std::fs::write(
        &path,
        file(
            &[("format", "profuse.features"), ("format_version", "1.0")],
            &[
                ("features", "F32", &[0, 1 << 62], b""),
                ("valid", "U8", &[0], b""),
            ],
        ),
    )
    .unwrap();
    let report = inspect(&path);
    assert!(report.error.is_none(), "{:?}", report.error);
    assert_eq!(
        report.json["tensors"]["features"]["shape"],
        serde_json::json!([0u64, 1u64 << 62])
    );
    assert_eq!(report.json["counts"]["feature_dim"], 1u64 << 62);
}
