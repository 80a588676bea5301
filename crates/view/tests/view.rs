//! Tests of profuse-view: the `.splat` converter against closed forms, the camera presets
//! against the cameras' own projection through gsplat.js's camera formulas, the typed
//! errors, the selection answers against the query library, click-only scoring (an
//! output without prompts) against a brute-force cosine, and (with
//! PROFUSE_REQUIRE_BROWSER=1) the page in headless Chromium on the synth demo output.

#![allow(clippy::unwrap_used, clippy::expect_used)]
#![allow(clippy::needless_range_loop)]

use std::io::{Read, Write};
use std::net::{IpAddr, Ipv4Addr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use profuse_formats::camera::{quaternion_to_rotation, SH_C0};
use profuse_formats::{Cameras, FileKind, Gaussians, Prompts, ViewMaps};
use profuse_query::{score_prompts, select, Descriptors, Rule, ScoreKind};
use profuse_view::{
    answer, listen, percent_decode, presets, respond, rotation_to_quaternion, splat_bytes,
    ScoringPaths, ViewError, ViewScene, DEFAULT_CLICK_COSINE_THRESHOLD, SPLAT_ROW_BYTES,
};

const LOCALHOST: IpAddr = IpAddr::V4(Ipv4Addr::LOCALHOST);

fn f32_at(row: &[u8], i: usize) -> f32 {
    f32::from_le_bytes(row[4 * i..4 * i + 4].try_into().unwrap())
}

#[test]
fn splat_rows_follow_the_closed_forms() {
    // Colour 0.5 + C0·dc: dc = 0 gives 0.5 (127.5 rounds to 128); dc = 0.5/C0 gives 1;
    // dc = -0.5/C0 gives 0; dc = 0.25/C0 gives 0.75 (191.25 -> 191).
    let c0 = SH_C0 as f32;
    let g = Gaussians {
        means: vec![[1.0, -2.0, 3.5], [0.0, 0.0, 0.0], [-7.25, 0.5, 1e3]].into(),
        log_scales: vec![[0.0, 1.0, -2.0], [-5.0, -5.0, -5.0], [0.5, 0.25, 0.125]].into(),
        rotations: vec![
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 2.0],
            [1.0, 1.0, 0.0, 0.0],
        ]
        .into(),
        opacity_logits: vec![0.0, 20.0, (0.25f32 / 0.75).ln()].into(),
        sh_dc: vec![[0.0, 0.5 / c0, -0.5 / c0], [0.25 / c0, 5.0, -5.0], [0.0; 3]].into(),
        ..Gaussians::default()
    };
    let bytes = splat_bytes(&g);
    assert_eq!(bytes.len(), 3 * SPLAT_ROW_BYTES);
    let rows: Vec<&[u8]> = bytes.chunks(SPLAT_ROW_BYTES).collect();
    for (i, row) in rows.iter().enumerate() {
        for a in 0..3 {
            assert_eq!(f32_at(row, a), g.means[i][a]);
            assert_eq!(f32_at(row, 3 + a), g.log_scales[i][a].exp());
        }
    }
    assert_eq!(&rows[0][24..28], &[128, 255, 0, 128]);
    assert_eq!(&rows[1][24..28], &[191, 255, 0, 255]);
    // opacity sigmoid(ln(1/3)) = 0.25 -> 63.75 -> 64
    assert_eq!(&rows[2][24..28], &[128, 128, 128, 64]);
    // Rotation bytes: round(q/|q|·128 + 128), clamped: identity (1,0,0,0) -> (255,128,128,128)
    // (256 clamps); z-axis half turn given unnormalised as (0,0,0,2) -> (128,128,128,255);
    // (1,1,0,0)/√2 -> 128 + 90.51 = 218.5 -> 219.
    assert_eq!(&rows[0][28..32], &[255, 128, 128, 128]);
    assert_eq!(&rows[1][28..32], &[128, 128, 128, 255]);
    assert_eq!(&rows[2][28..32], &[219, 219, 128, 128]);
}

/// A camera looking from `centre` with world-to-camera rotation `r` (rows: the camera axes).
fn camera(r: [[f64; 3]; 3], centre: [f64; 3], intrinsics: [f64; 4], size: [u32; 2]) -> Cameras {
    let t: Vec<f64> = (0..3)
        .map(|i| -(0..3).map(|j| r[i][j] * centre[j]).sum::<f64>())
        .collect();
    let row = [
        r[0][0], r[0][1], r[0][2], t[0], r[1][0], r[1][1], r[1][2], t[1], r[2][0], r[2][1],
        r[2][2], t[2],
    ];
    Cameras {
        image_names: vec!["images/v.png".into()],
        image_size: vec![size].into(),
        intrinsics: vec![intrinsics].into(),
        world_to_camera: vec![row].into(),
        distortion: None,
        extra: Default::default(),
    }
}

/// gsplat.js 1.2.9's camera, transcribed: R = Matrix3.RotationFromQuaternion(x, y, z, w)
/// (row-major), view = [Rᵀ | −Rᵀp], projection (2fx/W x, −2fy/H y, ·, z) on a W×H canvas,
/// then WebGL's viewport (row = (1 − ndc_y)/2·H), shifted by the canvas origin.
fn gsplat_pixel(p: &profuse_view::Preset, world: [f64; 3]) -> [f64; 2] {
    let [x, y, z, w] = p.rotation_xyzw;
    let r = [
        [
            1.0 - 2.0 * y * y - 2.0 * z * z,
            2.0 * x * y - 2.0 * z * w,
            2.0 * x * z + 2.0 * y * w,
        ],
        [
            2.0 * x * y + 2.0 * z * w,
            1.0 - 2.0 * x * x - 2.0 * z * z,
            2.0 * y * z - 2.0 * x * w,
        ],
        [
            2.0 * x * z - 2.0 * y * w,
            2.0 * y * z + 2.0 * x * w,
            1.0 - 2.0 * x * x - 2.0 * y * y,
        ],
    ];
    let d: Vec<f64> = (0..3).map(|i| world[i] - p.position[i]).collect();
    let cam: Vec<f64> = (0..3)
        .map(|j| (0..3).map(|i| r[i][j] * d[i]).sum())
        .collect();
    let (cw, ch) = (f64::from(p.canvas_size[0]), f64::from(p.canvas_size[1]));
    let ndc = [
        2.0 * p.fx / cw * cam[0] / cam[2],
        -2.0 * p.fy / ch * cam[1] / cam[2],
    ];
    [
        (ndc[0] + 1.0) / 2.0 * cw + p.canvas_origin[0] as f64,
        (1.0 - ndc[1]) / 2.0 * ch + p.canvas_origin[1] as f64,
    ]
}

#[test]
fn presets_project_points_where_the_cameras_do() {
    // A tilted camera with fx != fy and a principal point 12 px right of and 7 px above
    // the image centre (whole pixels, so the canvas shift is exact).
    let q = [0.9, 0.2, -0.3, 0.25];
    let r = quaternion_to_rotation(q).unwrap();
    let cameras = camera(
        r,
        [0.5, -1.0, 2.0],
        [300.0, 280.0, 172.0, 113.0],
        [320, 240],
    );
    let preset = &presets(&cameras)[0];
    assert_eq!(preset.principal_offset, [12.0, -7.0]);
    assert_eq!(preset.canvas_size, [344, 254]);
    for world in [
        [0.5, -1.0, 5.0],
        [1.3, 0.2, 4.0],
        [-0.7, -1.9, 3.1],
        [2.0, 1.0, -1.0],
    ] {
        let expected = cameras.project(0, world);
        if expected[2] <= 0.0 {
            continue;
        }
        let got = gsplat_pixel(preset, world);
        for a in 0..2 {
            assert!(
                (got[a] - expected[a]).abs() < 1e-9,
                "{world:?}: {got:?} vs {expected:?}"
            );
        }
    }
}

#[test]
fn rotation_to_quaternion_inverts_the_formats_rotation() {
    for q in [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.1, 0.2, 0.9, -0.3],
        [0.0, 0.0, 0.6, 0.8],
    ] {
        let r = quaternion_to_rotation(q).unwrap();
        let [x, y, z, w] = rotation_to_quaternion(&r);
        let back = quaternion_to_rotation([w, x, y, z]).unwrap();
        for i in 0..3 {
            for j in 0..3 {
                assert!((back[i][j] - r[i][j]).abs() < 1e-12);
            }
        }
    }
}

#[test]
fn a_directory_without_outputs_names_the_missing_file() {
    let dir = tempfile::tempdir().unwrap();
    let err = ViewScene::open(dir.path()).unwrap_err();
    let ViewError::NotPipelineOutput { missing, .. } = &err else {
        panic!("{err}")
    };
    assert_eq!(
        missing,
        &dir.path().join("out").join("gaussians.safetensors")
    );
    std::fs::create_dir(dir.path().join("out")).unwrap();
    std::fs::write(dir.path().join("out/gaussians.safetensors"), b"x").unwrap();
    std::fs::write(dir.path().join("cameras.safetensors"), b"x").unwrap();
    let err = ViewScene::open(dir.path()).unwrap_err();
    let ViewError::NotPipelineOutput { missing, .. } = &err else {
        panic!("{err}")
    };
    assert_eq!(missing, &dir.path().join("prompts.safetensors"));
    assert!(err.to_string().contains("prompts.safetensors"), "{err}");
}

#[test]
fn gaussians_only_shows_the_fox_layout_without_prompts() {
    // examples/fox.sh writes OUT/gaussians.safetensors and OUT/scene/cameras.safetensors.
    let dir = tempfile::tempdir().unwrap();
    let err = profuse_view::OutputPaths::find_gaussians_only(dir.path()).unwrap_err();
    assert!(matches!(err, ViewError::NotPipelineOutput { .. }), "{err}");
    let g = Gaussians {
        means: vec![[0.0, 0.0, 3.0]].into(),
        log_scales: vec![[-2.0; 3]].into(),
        rotations: vec![[1.0, 0.0, 0.0, 0.0]].into(),
        opacity_logits: vec![1.0].into(),
        sh_dc: vec![[0.1, 0.2, 0.3]].into(),
        ..Gaussians::default()
    };
    g.write(dir.path().join("gaussians.safetensors")).unwrap();
    std::fs::create_dir(dir.path().join("scene")).unwrap();
    let cameras = camera(IDENTITY, [0.0; 3], [100.0, 100.0, 32.0, 24.0], [64, 48]);
    cameras
        .write(dir.path().join("scene/cameras.safetensors"))
        .unwrap();
    let paths = profuse_view::OutputPaths::find_gaussians_only(dir.path()).unwrap();
    let scene = ViewScene::open_paths(paths).unwrap();
    let info = scene.info();
    assert_eq!(
        (info.gaussians, info.prompts.len(), info.click),
        (1, 0, false)
    );
    assert_eq!(info.views[0].position, [0.0; 3]);
    assert_eq!(scene.splat(), splat_bytes(&g).as_slice());
    assert_eq!(
        answer(&scene, "/api/select?prompt=sofa&threshold=0.5").status,
        400
    );
    // Without the scene's files next to it, it is not a pipeline output.
    let err = ViewScene::open(dir.path()).unwrap_err();
    assert!(matches!(err, ViewError::NotPipelineOutput { .. }), "{err}");
}

const IDENTITY: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// Descriptor dimension of the click-only scene (SAM's image embedding) and its PQ layout.
const SAM_DIM: usize = 256;
const PQ_M: usize = 4;
const PQ_KSUB: usize = 256;

/// The click-only scene's Gaussians: (a₀, a₁, a₆₄), the decoded descriptor a₀e₀ + a₁e₁ +
/// a₆₄e₆₄ (mask 0's feature is e₀, mask 1's e₁), and whether it has one. Cosines with e₀:
/// 1, .968, .929, .912, .888, .8, .954 (norm 2), 0, .1, −.5, none, .30, none (decodes to
/// zero); with e₁: .6 for Gaussian 5, 1 for 7, .949 for 8, .30 for 11, 0 for the others.
/// None lies within 0.01 of a threshold the test uses.
const CLICK_ONLY_DESCRIPTORS: [([f32; 3], bool); 13] = [
    ([1.0, 0.0, 0.0], true),
    ([0.97, 0.0, 0.25], true),
    ([0.93, 0.0, 0.37], true),
    ([0.91, 0.0, 0.41], true),
    ([0.89, 0.0, 0.46], true),
    ([0.8, 0.6, 0.0], true),
    ([1.9, 0.0, 0.6], true),
    ([0.0, 1.0, 0.0], true),
    ([0.1, 0.95, 0.3], true),
    ([-0.5, 0.0, 0.87], true),
    ([1.0, 0.0, 0.0], false),
    ([0.3, 0.3, 0.9], true),
    ([0.0, 0.0, 0.0], true),
];

/// A `profuse run` output of a scene without `prompts.safetensors` (what `profuse prepare`
/// makes without a CLIP text encoder): one 64 × 48 view looking down +z, 13 Gaussians in a
/// row at depth 3 (0-6 on the left half, 7-12 on the right), masks with 256-d
/// SAM-embedding-like features (mask 0 = left half, feature e₀; mask 1 = right half, e₁),
/// one proposal per mask, and PQ codes (M = 4, dsub = 64) that decode exactly to
/// [`CLICK_ONLY_DESCRIPTORS`]. Writes SCENE/cameras, OUT/gaussians and OUT/pq, and with
/// `click` also SCENE/masks and OUT/proposals.
fn write_click_only_output(dir: &Path, click: bool) {
    let n = CLICK_ONLY_DESCRIPTORS.len();
    let out = dir.join("out");
    std::fs::create_dir_all(&out).unwrap();
    let cameras = camera(IDENTITY, [0.0; 3], [100.0, 100.0, 32.0, 24.0], [64, 48]);
    cameras.write(dir.join("cameras.safetensors")).unwrap();
    let g = Gaussians {
        means: (0..n)
            .map(|i| [((2.0 + 4.8 * i as f32) - 32.0) / 100.0 * 3.0, 0.0, 3.0])
            .collect::<Vec<_>>()
            .into(),
        log_scales: vec![[-3.5; 3]; n].into(),
        rotations: vec![[1.0, 0.0, 0.0, 0.0]; n].into(),
        opacity_logits: vec![3.0; n].into(),
        sh_dc: vec![[0.2, 0.1, -0.1]; n].into(),
        ..Gaussians::default()
    };
    g.write(out.join("gaussians.safetensors")).unwrap();
    // Subspace 0 (dims 0..64) holds (a₀, a₁) in centroid i, subspace 1 (dims 64..128)
    // holds a₆₄ in centroid i; subspaces 2 and 3 use their zero centroid 0.
    let dsub = SAM_DIM / PQ_M;
    let mut centroids = vec![0.0f32; PQ_M * PQ_KSUB * dsub];
    let mut codes = vec![0u8; n * PQ_M];
    let mut norms = vec![0.0f32; n];
    let mut valid = vec![0u8; n];
    for (i, ([a0, a1, a64], has)) in CLICK_ONLY_DESCRIPTORS.iter().enumerate() {
        centroids[i * dsub] = *a0;
        centroids[i * dsub + 1] = *a1;
        centroids[(PQ_KSUB + i) * dsub] = *a64;
        codes[i * PQ_M] = i as u8;
        codes[i * PQ_M + 1] = i as u8;
        if *has {
            valid[i] = 1;
            norms[i] = (a0 * a0 + a1 * a1 + a64 * a64).sqrt();
        }
    }
    let pq = profuse_formats::Pq {
        m: PQ_M,
        dsub,
        centroids: centroids.into(),
        codes: codes.into(),
        norms: norms.into(),
        valid: valid.into(),
        extra: Default::default(),
    };
    pq.write(out.join("pq.safetensors")).unwrap();
    if !click {
        return;
    }
    let labels: Vec<u16> = (0..48 * 64).map(|p| u16::from(p % 64 >= 32)).collect();
    let mut features = vec![0.0f32; 2 * SAM_DIM];
    features[0] = 1.0;
    features[SAM_DIM + 1] = 1.0;
    let masks = profuse_formats::Masks {
        view_names: cameras.image_names.clone(),
        width: 64,
        height: 48,
        labels: profuse_formats::Labels::U16(labels.into()),
        mask_offsets: vec![0, 2].into(),
        features: profuse_formats::Floats::F32(features.into()),
        dim: SAM_DIM,
        extra: Default::default(),
    };
    masks.write(dir.join("masks.safetensors")).unwrap();
    let proposals = profuse_formats::Proposals {
        mask_proposal: vec![0, 1].into(),
        proposal_size: vec![1, 1].into(),
        proposal_views: vec![1, 1].into(),
        mask_share: None,
        mask_instance: None,
        extra: Default::default(),
    };
    proposals.write(out.join("proposals.safetensors")).unwrap();
}

/// The ids of a selection answer.
fn answered_ids(got: &profuse_view::Answer) -> Vec<u32> {
    assert_eq!(got.status, 200, "{}", String::from_utf8_lossy(&got.body));
    got.body
        .chunks(4)
        .map(|c| u32::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

#[test]
fn an_output_without_prompts_answers_clicks_by_cosine() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    // PQ codes but neither prompts nor masks and proposals: still not a pipeline output
    // (view it with --gaussians-only), naming the prompts file as before.
    write_click_only_output(root, false);
    let err = ViewScene::open(root).unwrap_err();
    let ViewError::NotPipelineOutput { missing, .. } = &err else {
        panic!("{err}")
    };
    assert_eq!(missing, &root.join("prompts.safetensors"));
    let paths = profuse_view::OutputPaths::find_gaussians_only(root).unwrap();
    assert!(ViewScene::open_paths(paths).is_ok());

    write_click_only_output(root, true);
    let scene = ViewScene::open(root).unwrap();
    assert_eq!(
        scene.paths().scoring,
        ScoringPaths::ClickCosine {
            pq: root.join("out/pq.safetensors")
        }
    );
    let info = scene.info();
    assert_eq!(
        (info.gaussians, info.prompts.len(), info.click, info.score),
        (CLICK_ONLY_DESCRIPTORS.len(), 0, true, "cosine")
    );
    assert_eq!(info.mode, "click_only");
    assert_eq!(info.default_threshold, DEFAULT_CLICK_COSINE_THRESHOLD);
    assert_eq!(DEFAULT_CLICK_COSINE_THRESHOLD, 0.9);
    let json: serde_json::Value =
        serde_json::from_slice(&answer(&scene, "/api/scene").body).unwrap();
    assert_eq!(json["score"], "cosine");
    assert_eq!(json["prompts"], serde_json::json!([]));
    assert_eq!(json["click"], true);
    assert_eq!(json["default_threshold"].as_f64().unwrap() as f32, 0.9);

    // A click selects exactly the Gaussians whose decoded PQ descriptor has cosine >= T
    // with the clicked mask's proposal descriptor (brute force in f64).
    let pq = profuse_formats::Pq::read(root.join("out/pq.safetensors")).unwrap();
    let decoded = |g: usize| -> Vec<f32> {
        (0..pq.m)
            .flat_map(|j| {
                let c = pq.codes[g * pq.m + j] as usize;
                pq.centroids[(j * PQ_KSUB + c) * pq.dsub..][..pq.dsub].to_vec()
            })
            .collect()
    };
    let cases: [(f64, usize, f32, &[u32]); 4] = [
        (16.5, 0, 0.9, &[0, 1, 2, 3, 6]),
        (16.5, 0, 0.5, &[0, 1, 2, 3, 4, 5, 6]),
        (48.5, 1, 0.9, &[7, 8]),
        (48.5, 1, 0.25, &[5, 7, 8, 11]),
    ];
    for (x, mask, threshold, expected) in cases {
        let url = format!("/api/click?view=0&x={x}&y=24.5&threshold={threshold}");
        let got = answer(&scene, &url);
        let ids = answered_ids(&got);
        let header = &got.headers.iter().find(|(k, _)| *k == "X-Click").unwrap().1;
        assert!(header.contains("\"source\":\"proposal\""), "{header}");
        let click = profuse_query::Click {
            view: 0,
            x,
            y: 24.5,
        };
        let (target, same) = scene.select_click(click, threshold).unwrap();
        assert_eq!(same, ids);
        assert_eq!(
            (target.mask, target.proposal),
            (mask as u32, Some(mask as u32))
        );
        // A one-mask proposal's descriptor is its mask's feature, e_mask.
        for (d, v) in target.embedding.iter().enumerate() {
            let want = if d == mask { 1.0 } else { 0.0 };
            assert!((v - want).abs() < 1e-6, "dim {d}: {v}");
        }
        let q: Vec<f64> = target.embedding.iter().map(|v| f64::from(*v)).collect();
        let brute: Vec<u32> = (0..pq.len())
            .filter(|&g| {
                let x = decoded(g);
                let dot: f64 = x.iter().zip(&q).map(|(a, b)| f64::from(*a) * b).sum();
                let norm = x.iter().map(|a| f64::from(*a).powi(2)).sum::<f64>().sqrt();
                pq.valid[g] == 1 && norm > 0.0 && dot / norm >= f64::from(threshold)
            })
            .map(|g| g as u32)
            .collect();
        assert_eq!(ids, brute, "click at x {x}, threshold {threshold}");
        assert_eq!(ids, expected, "click at x {x}, threshold {threshold}");
    }

    // The export of a click's selection works without prompts too.
    let got = answer(&scene, "/api/export.ply?view=0&x=16.5&y=24.5&threshold=0.9");
    assert_eq!(got.status, 200, "{}", String::from_utf8_lossy(&got.body));
    let ply = root.join("selection.ply");
    std::fs::write(&ply, &got.body).unwrap();
    assert_eq!(scene_io::read_inria_ply(&ply).unwrap().0.len(), 5);

    // Text prompts: a 400 saying the scene has none.
    let got = answer(&scene, "/api/select?prompt=sofa&threshold=0.5");
    assert_eq!(got.status, 400);
    let text = String::from_utf8_lossy(&got.body);
    assert!(text.contains("no text prompts"), "{text}");
    let err = scene.select_prompt("sofa", 0.5).unwrap_err();
    let ViewError::BadRequest { name, reason } = &err else {
        panic!("{err}")
    };
    assert_eq!(name, "prompt");
    assert!(reason.contains("no text prompts"), "{reason}");
    let got = answer(&scene, "/api/export.ply?prompt=sofa&threshold=0.5");
    assert_eq!(got.status, 400);
}

#[test]
fn a_taken_port_is_a_typed_error() {
    let taken = TcpListener::bind((LOCALHOST, 0)).unwrap();
    let port = taken.local_addr().unwrap().port();
    let err = listen(LOCALHOST, port).unwrap_err();
    assert!(matches!(err, ViewError::PortInUse { .. }), "{err}");
    assert!(
        err.to_string().contains(&format!("127.0.0.1:{port}")),
        "{err}"
    );
    let free = listen(LOCALHOST, 0).unwrap();
    assert!(free.addr().ip().is_loopback());
}

#[test]
fn percent_decoding() {
    assert_eq!(percent_decode("coffee%20table"), "coffee table");
    assert_eq!(percent_decode("a+b%2Fc%zz%4"), "a b/c%zz%4");
    assert_eq!(percent_decode("%C3%A9"), "é");
}

/// The synth demo output (scene and `out/`), generated once for the whole binary.
fn demo() -> &'static Path {
    static DEMO: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    let (_, scene) = DEMO.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        // PROFUSE_VIEW_DEMO keeps the demo between runs (the demo reruns nothing when
        // its scene and outputs are up to date).
        let scene = std::env::var_os("PROFUSE_VIEW_DEMO")
            .map_or_else(|| dir.path().join("demo"), PathBuf::from);
        let mut opts = profuse_experiments::demo::DemoOptions::new(0).unwrap();
        opts.scene = Some(scene.clone());
        profuse_experiments::demo::run_demo(&opts, &|_| {}, &|_| {}).unwrap();
        (dir, scene)
    });
    scene
}

fn demo_scene() -> &'static ViewScene {
    static SCENE: OnceLock<ViewScene> = OnceLock::new();
    SCENE.get_or_init(|| ViewScene::open(demo()).unwrap())
}

#[test]
fn selections_are_the_query_librarys() {
    let scene = demo_scene();
    let out = demo().join("out");
    let pq = profuse_formats::Pq::read(out.join("pq.safetensors")).unwrap();
    let prompts = Prompts::read(demo().join("prompts.safetensors")).unwrap();
    let info = scene.info();
    assert!(
        info.prompts.iter().any(|p| p == "sofa"),
        "{:?}",
        info.prompts
    );
    assert!(!info.prompts.iter().any(|p| p == "object"));
    for (name, threshold) in [("sofa", 0.5f32), ("sofa", 0.6), ("table", 0.5)] {
        let row = prompts.index_of(name).unwrap();
        let scores =
            score_prompts(Descriptors::Pq(&pq), &prompts, &[row], ScoreKind::Relevancy).unwrap();
        let expected = select(&scores[0], Rule::Threshold(threshold)).unwrap().ids;
        assert!(!expected.is_empty());
        let got = answer(
            scene,
            &format!("/api/select?prompt={name}&threshold={threshold}"),
        );
        assert_eq!(got.status, 200);
        let ids: Vec<u32> = got
            .body
            .chunks(4)
            .map(|c| u32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        assert_eq!(ids, expected, "{name} at {threshold}");
    }
    assert_eq!(
        answer(scene, "/api/select?prompt=nope&threshold=0.5").status,
        400
    );
    assert_eq!(
        answer(scene, "/api/select?prompt=sofa&threshold=x").status,
        400
    );
    assert_eq!(answer(scene, "/api/select?prompt=sofa").status, 400);
    assert_eq!(answer(scene, "/etc/passwd").status, 404);
    let gaussians = Gaussians::read(out.join("gaussians.safetensors")).unwrap();
    assert_eq!(answer(scene, "/scene.splat").body, splat_bytes(&gaussians));

    // The export is the selection's Gaussians, in id order, as an INRIA PLY.
    let ids = scene.select_prompt("sofa", 0.5).unwrap();
    let got = answer(scene, "/api/export.ply?prompt=sofa&threshold=0.5");
    assert_eq!(got.status, 200);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sofa.ply");
    std::fs::write(&path, &got.body).unwrap();
    let (subset, _) = scene_io::read_inria_ply(&path).unwrap();
    assert_eq!(subset.len(), ids.len());
    for (k, &id) in ids.iter().enumerate() {
        assert_eq!(subset.means[k], gaussians.means[id as usize]);
        assert_eq!(subset.sh_dc[k], gaussians.sh_dc[id as usize]);
    }
}

#[test]
fn a_click_on_the_sofa_selects_like_the_query_tool() {
    let scene = demo_scene();
    let (view, sofa) = sofa_view();
    let maps = ViewMaps::read(demo().join("gt/views.safetensors")).unwrap();
    // The sofa pixel nearest its mask's centroid that is on the sofa.
    let pixels = object_pixels(&maps, view, sofa);
    let n = pixels.len() as f64;
    let cx = pixels.iter().map(|p| p.0 as f64).sum::<f64>() / n;
    let cy = pixels.iter().map(|p| p.1 as f64).sum::<f64>() / n;
    let &(x, y) = pixels
        .iter()
        .min_by(|a, b| dist(**a, cx, cy).total_cmp(&dist(**b, cx, cy)))
        .unwrap();
    let url = format!("/api/click?view={view}&x={}.5&y={}.5&threshold=0.5", x, y);
    let got = answer(scene, &url);
    assert_eq!(got.status, 200, "{}", String::from_utf8_lossy(&got.body));
    let header = &got.headers.iter().find(|(k, _)| *k == "X-Click").unwrap().1;
    assert!(header.contains("\"source\":\"proposal\""), "{header}");
    let outside = format!("/api/click?view={view}&x=-5&y=3&threshold=0.5");
    assert_eq!(answer(scene, &outside).status, 400);
    assert_eq!(
        answer(scene, "/api/click?view=999&x=1&y=1&threshold=0.5").status,
        400
    );
    let ids: Vec<u32> = got
        .body
        .chunks(4)
        .map(|c| u32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    // The clicked sofa's selection overlaps the "sofa" prompt's by more than half.
    let sofa_ids = scene.select_prompt("sofa", 0.5).unwrap();
    let common = ids
        .iter()
        .filter(|i| sofa_ids.binary_search(i).is_ok())
        .count();
    assert!(
        2 * common > ids.len().min(sofa_ids.len()),
        "{common} of {} / {}",
        ids.len(),
        sofa_ids.len()
    );
}

fn dist(p: (usize, usize), cx: f64, cy: f64) -> f64 {
    (p.0 as f64 - cx).powi(2) + (p.1 as f64 - cy).powi(2)
}

/// The view where the sofa covers most pixels, and the sofa's object index.
fn sofa_view() -> (usize, u32) {
    let truth =
        profuse_formats::ground_truth::SceneTruth::read(demo().join("gt/scene.json")).unwrap();
    let sofa = truth
        .objects
        .iter()
        .find(|o| o.class_name == "sofa")
        .unwrap()
        .index;
    let maps = ViewMaps::read(demo().join("gt/views.safetensors")).unwrap();
    let views = maps.view_names.len();
    let best = (0..views)
        .max_by_key(|&v| (object_pixels(&maps, v, sofa).len(), std::cmp::Reverse(v)))
        .unwrap();
    (best, sofa)
}

/// (column, row) of every pixel of view `v` showing object `object`.
fn object_pixels(maps: &ViewMaps, v: usize, object: u32) -> Vec<(usize, usize)> {
    let ids = maps.object_ids.as_ref().unwrap();
    let (w, h) = (maps.width, maps.height);
    (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .filter(|&(x, y)| ids[(v * h + y) * w + x] == object)
        .collect()
}

/// A GET over a real socket: (status line, body).
fn http_get(addr: std::net::SocketAddr, path: &str) -> (String, Vec<u8>) {
    let mut s = TcpStream::connect(addr).unwrap();
    write!(s, "GET {path} HTTP/1.0\r\nHost: localhost\r\n\r\n").unwrap();
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).unwrap();
    let split = raw.windows(4).position(|w| w == b"\r\n\r\n").unwrap();
    let head = String::from_utf8_lossy(&raw[..split]).to_string();
    (
        head.lines().next().unwrap().to_string(),
        raw[split + 4..].to_vec(),
    )
}

#[test]
fn the_server_answers_over_http() {
    let listener = listen(LOCALHOST, 0).unwrap();
    let addr = listener.addr();
    std::thread::spawn(move || listener.serve(demo_scene()));
    let (status, body) = http_get(addr, "/");
    assert!(status.contains("200"), "{status}");
    assert!(String::from_utf8_lossy(&body).contains("/app.js"));
    let (status, body) = http_get(addr, "/api/scene");
    assert!(status.contains("200"), "{status}");
    let info: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(
        info["gaussians"].as_u64().unwrap() as usize * 32,
        demo_scene().splat().len()
    );
    let (status, _) = http_get(addr, "/gsplat.js");
    assert!(status.contains("200"), "{status}");
}

#[test]
fn the_vendored_gsplat_is_the_locked_package() {
    // When `npm ci` has run in web/, the served bundle must be the installed one.
    let web = Path::new(env!("CARGO_MANIFEST_DIR")).join("web");
    let installed = web.join("node_modules/gsplat/dist/index.es.js");
    let vendored = std::fs::read(web.join("vendor/gsplat.js")).unwrap();
    assert!(vendored.len() > 100_000);
    match std::fs::read(&installed) {
        Ok(bytes) => assert!(bytes == vendored, "run `npm run vendor` in crates/view/web"),
        Err(_) => eprintln!("{} absent: not compared", installed.display()),
    }
}

/// Pixels the page tinted magenta: red and blue well above green and close to each other
/// (grey others keep r = g = b; a magenta splat over them or the black background raises
/// red and blue together).
fn tinted_pixels(png: &Path) -> (Vec<bool>, u32, u32) {
    let img = image::open(png).unwrap().to_rgb8();
    let tinted = img
        .pixels()
        .map(|p| {
            let [r, g, b] = p.0.map(i32::from);
            r.min(b) - g >= 64 && (r - b).abs() <= 40
        })
        .collect();
    (tinted, img.width(), img.height())
}

fn iou(a: &[bool], b: &[bool]) -> f64 {
    let inter = a.iter().zip(b).filter(|(x, y)| **x && **y).count();
    let union = a.iter().zip(b).filter(|(x, y)| **x || **y).count();
    inter as f64 / union.max(1) as f64
}

/// Runs `node web/drive.mjs ARGS…` and returns its stdout.
fn drive(args: &[&str]) -> String {
    let web = Path::new(env!("CARGO_MANIFEST_DIR")).join("web");
    let out = std::process::Command::new("node")
        .arg(web.join("drive.mjs"))
        .args(args)
        .current_dir(&web)
        .output()
        .expect("node runs");
    assert!(
        out.status.success(),
        "drive.mjs failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// The sofa selection on screen must fall on the sofa's ground-truth mask: measured 0.835
/// on the synth demo (seed 0, view 5, SwiftShader), asserted a little below.
const MIN_SOFA_IOU: f64 = 0.75;

#[test]
fn the_page_tints_the_sofa_in_chromium() {
    if std::env::var("PROFUSE_REQUIRE_BROWSER").as_deref() != Ok("1") {
        eprintln!(
            "skipped: set PROFUSE_REQUIRE_BROWSER=1 to run the page in headless Chromium \
             (needs /usr/bin/chromium and `npm ci` in crates/view/web)"
        );
        return;
    }
    let chromium = std::env::var("CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    assert!(
        Path::new(&chromium).is_file(),
        "{chromium} missing: apt-get install chromium"
    );
    let web = Path::new(env!("CARGO_MANIFEST_DIR")).join("web");
    assert!(
        web.join("node_modules/playwright-core").is_dir(),
        "run `npm ci` in {}",
        web.display()
    );
    let (view, sofa) = sofa_view();
    let listener = listen(LOCALHOST, 0).unwrap();
    let url = format!("{}?view={view}&prompt=sofa&others=grey", listener.url());
    std::thread::spawn(move || listener.serve(demo_scene()));
    let shots = tempfile::tempdir().unwrap();
    let dir = shots.path().to_str().unwrap();
    let report = drive(&["shots", &url, dir, SECOND_PROMPT]);
    eprintln!("drive.mjs: {report}");
    let report: serde_json::Value = serde_json::from_str(&report).unwrap();
    assert_eq!(
        report["errors"],
        serde_json::json!([]),
        "the page reported errors"
    );
    let (first, w, h) = tinted_pixels(&shots.path().join("first.png"));
    let (second, ..) = tinted_pixels(&shots.path().join("second.png"));
    let maps = ViewMaps::read(demo().join("gt/views.safetensors")).unwrap();
    assert_eq!((w as usize, h as usize), (maps.width, maps.height));
    let mut truth = vec![false; first.len()];
    for (x, y) in object_pixels(&maps, view, sofa) {
        truth[y * maps.width + x] = true;
    }
    let sofa_iou = iou(&first, &truth);
    let change = iou(&first, &second);
    eprintln!(
        "view {view}: sofa tinted {} px, ground truth {} px, IoU {sofa_iou:.3}; \
         {SECOND_PROMPT} tinted {} px, IoU with the sofa's {change:.3}",
        first.iter().filter(|t| **t).count(),
        truth.iter().filter(|t| **t).count(),
        second.iter().filter(|t| **t).count(),
    );
    if let Ok(keep) = std::env::var("PROFUSE_VIEW_SHOTS") {
        for name in ["first.png", "second.png"] {
            std::fs::copy(shots.path().join(name), Path::new(&keep).join(name)).unwrap();
        }
    }
    assert!(
        sofa_iou >= MIN_SOFA_IOU,
        "sofa IoU {sofa_iou:.3} < {MIN_SOFA_IOU}"
    );
    assert!(
        change < 0.5,
        "the second prompt left the selection unchanged (IoU {change:.3})"
    );
}

const SECOND_PROMPT: &str = "table";

/// The rules every request passes before its route (DNS rebinding, methods, headers), and
/// error bodies that name files without the server's folders.
#[test]
fn requests_from_other_hosts_or_methods_are_refused_and_answers_are_hardened() {
    let scene = demo_scene();
    let addr: std::net::SocketAddr = "127.0.0.1:8765".parse().unwrap();
    let get = |host: Option<&str>, url: &str| respond(scene, "GET", host, url, addr);
    for ok in [
        "127.0.0.1:8765",
        "localhost:8765",
        "LOCALHOST",
        "127.0.0.2:8765",
    ] {
        assert_eq!(get(Some(ok), "/api/scene").status, 200, "{ok}");
    }
    for refused in [
        None,
        Some("attacker.example:8765"),
        Some("attacker.example"),
        Some("localhost:80"),
        Some("127.0.0.1.attacker.example:8765"),
    ] {
        let a = get(refused, "/api/scene");
        assert_eq!(a.status, 421, "{refused:?}");
        assert!(!a.body.starts_with(b"{"), "{refused:?} got the scene");
    }
    let ipv6: std::net::SocketAddr = "[::1]:9000".parse().unwrap();
    assert_eq!(
        respond(scene, "GET", Some("[::1]:9000"), "/api/scene", ipv6).status,
        200
    );
    // Served beyond loopback on purpose: any Host.
    let wide: std::net::SocketAddr = "0.0.0.0:8765".parse().unwrap();
    assert_eq!(
        respond(scene, "GET", Some("viewer.lan:8765"), "/", wide).status,
        200
    );
    for method in ["POST", "DELETE", "OPTIONS", "PUT"] {
        let a = respond(scene, method, Some("localhost:8765"), "/api/scene", addr);
        assert_eq!(a.status, 405, "{method}");
        assert!(a
            .headers
            .iter()
            .any(|(n, v)| *n == "Allow" && v == "GET, HEAD"));
    }
    let a = get(Some("localhost:8765"), "/");
    for (name, value) in [
        ("X-Content-Type-Options", "nosniff"),
        ("X-Frame-Options", "DENY"),
        ("Content-Security-Policy", "frame-ancestors 'none'"),
        ("Referrer-Policy", "no-referrer"),
    ] {
        assert!(
            a.headers.iter().any(|(n, v)| *n == name && v == value),
            "{name}: {:?}",
            a.headers
        );
    }
    // A click on a view that does not exist: the error names the cameras file, not where
    // the server keeps it.
    let a = get(
        Some("localhost:8765"),
        "/api/click?view=9999&x=1&y=1&threshold=0.5",
    );
    assert_eq!(a.status, 400);
    let body = String::from_utf8_lossy(&a.body).to_string();
    assert!(body.contains("cameras.safetensors"), "{body}");
    let root = demo().display().to_string();
    assert!(!body.contains(&root), "{body}");
}

/// Masks of another scene are refused when the viewer opens (they used to be accepted and
/// then refuse every click); and a file copied over an input while the viewer runs cannot
/// kill it (inputs are read into memory, not mapped).
#[test]
fn inputs_of_another_scene_are_refused_and_replaced_files_do_not_kill_the_viewer() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    for f in [
        "cameras.safetensors",
        "masks.safetensors",
        "prompts.safetensors",
    ] {
        std::fs::copy(demo().join(f), root.join(f)).unwrap();
    }
    std::fs::create_dir_all(root.join("out")).unwrap();
    for f in [
        "gaussians.safetensors",
        "pq.safetensors",
        "proposals.safetensors",
    ] {
        std::fs::copy(demo().join("out").join(f), root.join("out").join(f)).unwrap();
    }
    let scene = ViewScene::open(root).unwrap();
    let export = "/api/export.ply?prompt=sofa&threshold=0.5";
    let before = answer(&scene, export);
    assert_eq!(before.status, 200);
    // `cp` over a mapped input truncates it in place: the next read of a mapped page
    // would raise SIGBUS. Read into memory, the viewer answers as before.
    std::fs::write(root.join("out/gaussians.safetensors"), b"x").unwrap();
    std::fs::write(root.join("out/pq.safetensors"), b"x").unwrap();
    let after = answer(&scene, export);
    assert_eq!(after.status, 200);
    assert_eq!(after.body, before.body);
    assert_eq!(answer(&scene, "/scene.splat").body, scene.splat());
    drop(scene);

    // The masks of a two-view scene against the demo's cameras.
    std::fs::copy(
        demo().join("out/gaussians.safetensors"),
        root.join("out/gaussians.safetensors"),
    )
    .unwrap();
    std::fs::copy(
        demo().join("out/pq.safetensors"),
        root.join("out/pq.safetensors"),
    )
    .unwrap();
    let other = profuse_formats::samples::masks();
    other.write(root.join("masks.safetensors")).unwrap();
    let err = ViewScene::open(root).unwrap_err();
    assert!(
        err.to_string().contains("masks.safetensors") && err.to_string().contains("views"),
        "{err}"
    );
}

/// Sends `raw` and returns the status line of the answer (empty when none came).
fn raw_status(addr: std::net::SocketAddr, raw: &[u8]) -> String {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(std::time::Duration::from_secs(20)))
        .unwrap();
    let _ = s.write_all(raw);
    let mut got = Vec::new();
    let _ = s.read_to_end(&mut got);
    String::from_utf8_lossy(&got)
        .lines()
        .next()
        .unwrap_or("")
        .to_string()
}

/// The server side of the limits (crates/view/src/http.rs): a POST declaring a 1 TB body
/// gets 405 at once and the server lives on (tiny_http allocated the declared length and
/// aborted); a header line over the limit gets 431; a client that connects and says
/// nothing does not hold up others; a malformed request line gets 400.
#[test]
fn the_server_survives_hostile_requests() {
    let listener = listen(LOCALHOST, 0).unwrap();
    let addr = listener.addr();
    std::thread::spawn(move || listener.serve(demo_scene()));
    let host = format!("Host: {addr}\r\n");
    let post =
        format!("POST /api/scene HTTP/1.1\r\n{host}Content-Length: 1000000000000\r\n\r\nabc");
    assert!(raw_status(addr, post.as_bytes()).contains("405"));
    let huge = format!(
        "GET / HTTP/1.1\r\n{host}X-Big: {}\r\n\r\n",
        "a".repeat(200_000)
    );
    assert!(raw_status(addr, huge.as_bytes()).contains("431"));
    assert!(raw_status(addr, b"NONSENSE\r\n\r\n").contains("400"));
    // Idle clients hold their own threads, not the server.
    let idle: Vec<TcpStream> = (0..8).map(|_| TcpStream::connect(addr).unwrap()).collect();
    let (status, body) = http_get(addr, "/api/scene");
    assert!(status.contains("200"), "{status}");
    assert!(serde_json::from_slice::<serde_json::Value>(&body).is_ok());
    drop(idle);
    let head = format!("HEAD /api/scene HTTP/1.1\r\n{host}\r\n");
    let mut s = TcpStream::connect(addr).unwrap();
    s.write_all(head.as_bytes()).unwrap();
    let mut got = Vec::new();
    s.read_to_end(&mut got).unwrap();
    let text = String::from_utf8_lossy(&got);
    assert!(text.starts_with("HTTP/1.1 200"), "{text}");
    assert!(text.ends_with("\r\n\r\n"), "HEAD carries no body: {text}");
}
