//! ScanNet: exported sensor folders → [`Cameras`]; `*_vh_clean_2.labels.ply` and the
//! NumPy vertex arrays → [`Mesh`].
//!
//! Conventions converted:
//! * `pose/<frame>.txt` is camera-to-world in OpenCV axes already; poses with NaN/inf
//!   (ScanNet marks tracking failures with `-inf`) are skipped with a warning.
//! * The axis alignment `A` of `<scene>.txt` (`axisAlignment = 16 numbers`, row-major)
//!   maps raw to aligned coordinates; poses become `c2w_aligned = A · c2w`. It is used
//!   by default when the file exists ([`AxisAlignment::Auto`]).
//! * `intrinsic/intrinsic_color.txt` holds K with pixel centres at integer coordinates
//!   (OpenCV calibration, and how ScanNet tools round projections to pixels), so
//!   `cx, cy` gain [`SCANNET_PRINCIPAL_POINT_SHIFT`] = 0.5 to reach our corner-origin
//!   convention.
//! * Mesh labels are NYU40 ids (`label_space = nyu40`), 0 = unannotated.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use profuse_formats::label_space::NYU40_SPACE;
use profuse_formats::{Cameras, FileKind, Mesh};
use serde::Serialize;

use crate::error::{invalid, missing, parse_err, Result};
use crate::fsutil::{image_dimensions, list_dir, read_text, show};
use crate::geometry::{
    mat4_mul, rotation_block, snap_to_rotation, translation_column, world_to_camera_from_c2w,
};
use crate::npy::{read_npy, NpyArray};
use crate::ply::{read_ply, Column, Element, Values};

/// Added to ScanNet's `cx`, `cy` (pixel centres at integers) to get ours (centres at +0.5).
pub const SCANNET_PRINCIPAL_POINT_SHIFT: f64 = 0.5;

/// A 4x4 row-major matrix.
pub type Mat4 = [[f64; 4]; 4];

/// Which axis alignment to apply to ScanNet poses.
#[derive(Debug, Clone, PartialEq)]
pub enum AxisAlignment {
    /// Use `SCENE_DIR/<dir name>.txt` when it exists, else none (with a warning).
    Auto,
    /// Keep raw ScanNet coordinates.
    Off,
    /// Apply this matrix.
    Matrix(Mat4),
}

/// Options of [`import_scannet_folder`].
#[derive(Debug, Clone, PartialEq)]
pub struct ScannetOptions {
    /// Keep every `stride`-th frame (in frame-number order, before skipping bad poses).
    pub stride: usize,
    /// Axis alignment of the poses.
    pub axis_alignment: AxisAlignment,
    /// Image width and height; `None` reads the first kept image's header.
    pub image_size: Option<[u32; 2]>,
}

impl Default for ScannetOptions {
    fn default() -> Self {
        ScannetOptions {
            stride: 1,
            axis_alignment: AxisAlignment::Auto,
            image_size: None,
        }
    }
}

/// What [`import_scannet_folder`] did.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ScannetReport {
    /// Colour frames found.
    pub frames: usize,
    /// Frames left after the stride.
    pub selected: usize,
    /// Views imported.
    pub views: usize,
    /// Selected frames skipped (invalid or missing pose).
    pub skipped: usize,
    /// Whether an axis alignment was applied.
    pub axis_aligned: bool,
    /// One line per skipped frame or missing optional input.
    pub warnings: Vec<String>,
}

/// Reads a ScanNet folder exported by the SensReader (`color/`, `pose/`, `intrinsic/`).
pub fn import_scannet_folder(
    dir: impl AsRef<Path>,
    options: &ScannetOptions,
) -> Result<(Cameras, ScannetReport)> {
    let dir = dir.as_ref();
    let label = show(dir);
    if options.stride == 0 {
        return Err(invalid(&label, "stride", "0, expected a frame stride >= 1"));
    }
    let mut warnings = Vec::new();
    let alignment = resolve_alignment(dir, &options.axis_alignment, &mut warnings)?;
    let frames = color_frames(dir)?;
    let selected: Vec<&(String, PathBuf)> = frames.iter().step_by(options.stride).collect();

    let k = read_matrix4(&dir.join("intrinsic").join("intrinsic_color.txt"))?;
    let intrinsics = [
        k[0][0],
        k[1][1],
        k[0][2] + SCANNET_PRINCIPAL_POINT_SHIFT,
        k[1][2] + SCANNET_PRINCIPAL_POINT_SHIFT,
    ];

    let mut names = Vec::new();
    let mut poses = Vec::new();
    let mut first_image = None;
    for (stem, image) in selected.iter().copied() {
        let pose_path = dir.join("pose").join(format!("{stem}.txt"));
        if !pose_path.is_file() {
            warnings.push(format!(
                "frame {stem}: {} not found; frame skipped",
                show(&pose_path)
            ));
            continue;
        }
        let c2w = read_matrix4(&pose_path)?;
        if c2w.iter().flatten().any(|v| !v.is_finite()) {
            warnings.push(format!(
                "frame {stem}: pose {} is not finite (tracking lost); frame skipped",
                show(&pose_path)
            ));
            continue;
        }
        let c2w = match &alignment {
            Some(a) => mat4_mul(a, &c2w),
            None => c2w,
        };
        let r = snap_to_rotation(&rotation_block(&c2w))
            .map_err(|e| invalid(&show(&pose_path), "camera-to-world rotation", e.to_string()))?;
        poses.push(world_to_camera_from_c2w(&r, translation_column(&c2w)));
        let file = image
            .file_name()
            .map(|f| f.to_string_lossy().into_owned())
            .unwrap_or_default();
        names.push(format!("color/{file}"));
        first_image.get_or_insert(image);
    }
    let Some(first_image) = first_image else {
        return Err(invalid(
            &label,
            "frames",
            "no selected frame has a valid pose",
        ));
    };
    let size = match options.image_size {
        Some(s) => s,
        None => image_dimensions(first_image)?,
    };
    let report = ScannetReport {
        frames: frames.len(),
        selected: selected.len(),
        views: names.len(),
        skipped: selected.len() - names.len(),
        axis_aligned: alignment.is_some(),
        warnings,
    };
    let n = names.len();
    let cameras = Cameras {
        image_names: names,
        image_size: vec![size; n].into(),
        intrinsics: vec![intrinsics; n].into(),
        world_to_camera: poses.into(),
        distortion: None,
        extra: BTreeMap::from([
            ("source".to_string(), "scannet".to_string()),
            ("axis_aligned".to_string(), report.axis_aligned.to_string()),
        ]),
    };
    Ok((cameras, report))
}

fn resolve_alignment(
    dir: &Path,
    choice: &AxisAlignment,
    warnings: &mut Vec<String>,
) -> Result<Option<Mat4>> {
    match choice {
        AxisAlignment::Off => Ok(None),
        AxisAlignment::Matrix(m) => Ok(Some(*m)),
        AxisAlignment::Auto => {
            let name = dir
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            let txt = dir.join(format!("{name}.txt"));
            if txt.is_file() {
                read_axis_alignment(&txt).map(Some)
            } else {
                warnings.push(format!(
                    "{} not found: poses stay in raw ScanNet coordinates",
                    show(&txt)
                ));
                Ok(None)
            }
        }
    }
}

/// `color/*.jpg|jpeg|png` as (stem, path), numerically sorted when every stem is a
/// number (ScanNet's `0.jpg, 1.jpg, ..., 10.jpg`), else by name.
fn color_frames(dir: &Path) -> Result<Vec<(String, PathBuf)>> {
    let color = dir.join("color");
    if !color.is_dir() {
        return Err(missing(
            &show(dir),
            "directory `color/`",
            "the colour frames of a ScanNet export",
        ));
    }
    let mut frames: Vec<(String, PathBuf)> = list_dir(&color)?
        .into_iter()
        .filter(|p| {
            p.extension()
                .map(|e| e.to_string_lossy().to_ascii_lowercase())
                .is_some_and(|e| matches!(e.as_str(), "jpg" | "jpeg" | "png"))
        })
        .filter_map(|p| Some((p.file_stem()?.to_string_lossy().into_owned(), p)))
        .collect();
    if frames.iter().all(|(s, _)| s.parse::<u64>().is_ok()) {
        frames.sort_by_key(|(s, _)| s.parse::<u64>().unwrap_or(u64::MAX));
    }
    if frames.is_empty() {
        return Err(missing(
            &show(&color),
            "colour frames",
            "*.jpg or *.png files",
        ));
    }
    Ok(frames)
}

/// Reads 16 whitespace-separated numbers (a 4x4 matrix, row-major). `inf`/`nan` parse
/// (ScanNet writes `-inf` poses); anything else that is not a number is an error.
pub fn read_matrix4(path: &Path) -> Result<Mat4> {
    let label = show(path);
    let text = read_text(path)?;
    let numbers = parse_numbers(&text, &label, "matrix entry")?;
    matrix_from(&numbers).ok_or_else(|| {
        invalid(
            &label,
            "matrix",
            format!("{} numbers, expected 16 (4x4)", numbers.len()),
        )
    })
}

fn parse_numbers(text: &str, label: &str, field: &str) -> Result<Vec<f64>> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        for token in line.split_ascii_whitespace() {
            out.push(
                token
                    .parse::<f64>()
                    .map_err(|_| parse_err(label, i + 1, field, "a number", token))?,
            );
        }
    }
    Ok(out)
}

fn matrix_from(numbers: &[f64]) -> Option<Mat4> {
    if numbers.len() != 16 {
        return None;
    }
    let mut m = [[0.0; 4]; 4];
    for (slot, v) in m.iter_mut().flatten().zip(numbers) {
        *slot = *v;
    }
    Some(m)
}

/// The `axisAlignment = ...` matrix of a ScanNet `<scene>.txt`.
pub fn read_axis_alignment(path: &Path) -> Result<Mat4> {
    let label = show(path);
    let text = read_text(path)?;
    for (i, line) in text.lines().enumerate() {
        let Some((key, value)) = line.split_once('=') else {
            continue;
        };
        if key.trim() != "axisAlignment" {
            continue;
        }
        let numbers = parse_numbers(value, &label, "axisAlignment")
            .map_err(|_| parse_err(&label, i + 1, "axisAlignment", "16 numbers", value.trim()))?;
        let m = matrix_from(&numbers)
            .filter(|m| m.iter().flatten().all(|v| v.is_finite()))
            .ok_or_else(|| {
                parse_err(
                    &label,
                    i + 1,
                    "axisAlignment",
                    "16 finite numbers",
                    value.trim(),
                )
            })?;
        snap_to_rotation(&rotation_block(&m))
            .map_err(|e| invalid(&label, "axisAlignment", e.to_string()))?;
        return Ok(m);
    }
    Err(missing(
        &label,
        "line `axisAlignment = ...`",
        "16 numbers, the row-major 4x4 alignment",
    ))
}

/// What a mesh import found.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct MeshReport {
    pub vertices: usize,
    pub faces: usize,
    /// Vertices with a label other than 0.
    pub labelled: usize,
    pub has_colors: bool,
    pub has_instances: bool,
}

impl MeshReport {
    fn of(mesh: &Mesh) -> MeshReport {
        MeshReport {
            vertices: mesh.vertices.len(),
            faces: mesh.faces.as_ref().map_or(0, |f| f.len()),
            labelled: mesh
                .labels
                .as_ref()
                .map_or(0, |l| l.iter().filter(|x| **x != 0).count()),
            has_colors: mesh.colors.is_some(),
            has_instances: mesh.instances.is_some(),
        }
    }
}

/// Reads a mesh with per-vertex ground-truth labels by path, whatever its source: a mesh
/// file (`.safetensors`, SPEC.md §4.12), a ScanNet `*.ply` ([`read_scannet_labels_ply`]),
/// or else a NumPy export ([`read_scannet_npy`]: a directory holding one `*_vert_all.npy`,
/// or that prefix). The ScanNet protocol's evaluators take any of these.
pub fn read_labelled_mesh(path: impl AsRef<Path>) -> Result<Mesh> {
    let path = path.as_ref();
    let name = path.to_string_lossy();
    if name.ends_with(".safetensors") {
        Ok(Mesh::read(path)?)
    } else if name.ends_with(".ply") {
        Ok(read_scannet_labels_ply(path)?.0)
    } else {
        Ok(read_scannet_npy(path)?.0)
    }
}

/// Reads `*_vh_clean_2.labels.ply` (vertex `x y z red green blue alpha label`, face
/// `vertex_indices`) in raw ScanNet coordinates (see [`align_mesh`]). Colours and labels
/// are optional, so the unlabelled `*_vh_clean_2.ply` reads too.
pub fn read_scannet_labels_ply(path: impl AsRef<Path>) -> Result<(Mesh, MeshReport)> {
    let path = path.as_ref();
    let label = show(path);
    let ply = read_ply(path)?;
    let vertex = ply
        .element("vertex")
        .ok_or_else(|| missing(&label, "element `vertex`", "the mesh vertices"))?;
    let get = |name: &str| {
        vertex.scalar(name).ok_or_else(|| {
            missing(
                &label,
                format!("vertex property `{name}`"),
                "a scalar property",
            )
        })
    };
    let (x, y, z) = (get("x")?, get("y")?, get("z")?);
    let vertices = (0..vertex.len())
        .map(|i| {
            let row = [x, y, z].map(|c| c.get_f32(i).unwrap_or(f32::NAN));
            match row.iter().position(|v| !v.is_finite()) {
                None => Ok(row),
                Some(axis) => Err(crate::error::SceneError::NonFinite {
                    path: label.clone(),
                    field: format!(
                        "vertex property `{}`",
                        ["x", "y", "z"].get(axis).copied().unwrap_or("x")
                    ),
                    index: i,
                    value: profuse_formats::format_float(f64::from(
                        row.get(axis).copied().unwrap_or(f32::NAN),
                    )),
                }),
            }
        })
        .collect::<Result<Vec<_>>>()?;
    let colors = match (
        vertex.scalar("red"),
        vertex.scalar("green"),
        vertex.scalar("blue"),
    ) {
        (Some(r), Some(g), Some(b)) => Some(
            (0..vertex.len())
                .map(|i| {
                    let mut rgb = [0u8; 3];
                    for ((slot, values), name) in
                        rgb.iter_mut().zip([r, g, b]).zip(["red", "green", "blue"])
                    {
                        *slot = byte(values, i).ok_or_else(|| {
                            invalid(
                                &label,
                                format!("vertex property `{name}`"),
                                format!("vertex {i}: expected an integer 0..=255"),
                            )
                        })?;
                    }
                    Ok(rgb)
                })
                .collect::<Result<Vec<_>>>()?,
        ),
        _ => None,
    };
    let labels = match vertex.scalar("label") {
        Some(values) => Some(unsigned_column(values, &label, "vertex property `label`")?),
        None => None,
    };
    let faces = match ply.element("face") {
        Some(face) => Some(triangles(face, vertices.len(), &label)?),
        None => None,
    };
    let file = path
        .file_name()
        .map(|f| f.to_string_lossy().into_owned())
        .unwrap_or_default();
    let mesh = Mesh {
        vertices: vertices.into(),
        colors: colors.map(Into::into),
        faces: faces.map(Into::into),
        labels: labels.map(Into::into),
        instances: None,
        extra: BTreeMap::from([
            ("label_space".to_string(), NYU40_SPACE.to_string()),
            ("source".to_string(), format!("scannet:{file}")),
        ]),
    };
    let report = MeshReport::of(&mesh);
    Ok((mesh, report))
}

fn byte(values: &Values, i: usize) -> Option<u8> {
    let v = values.get(i)?;
    (v.fract() == 0.0 && (0.0..=255.0).contains(&v)).then_some(v as u8)
}

fn unsigned_column(values: &Values, label: &str, field: &str) -> Result<Vec<u32>> {
    (0..values.len())
        .map(|i| {
            let v = values.get(i).unwrap_or(f64::NAN);
            if v.fract() == 0.0 && (0.0..=f64::from(u32::MAX)).contains(&v) {
                Ok(v as u32)
            } else {
                Err(invalid(
                    label,
                    field,
                    format!("element {i} is {v}, expected an integer 0..=4294967295"),
                ))
            }
        })
        .collect()
}

/// The `vertex_indices` (or `vertex_index`) lists as triangles with indices < `vertices`.
fn triangles(face: &Element, vertices: usize, label: &str) -> Result<Vec<[u32; 3]>> {
    let (name, column) = ["vertex_indices", "vertex_index"]
        .into_iter()
        .find_map(|n| face.column(n).map(|c| (n, c)))
        .ok_or_else(|| {
            missing(
                label,
                "face property `vertex_indices`",
                "a list of vertex indices per face",
            )
        })?;
    let Column::List { offsets, items } = column else {
        return Err(invalid(
            label,
            format!("face property `{name}`"),
            "is a scalar, expected a list",
        ));
    };
    let field = format!("face property `{name}`");
    offsets
        .windows(2)
        .enumerate()
        .map(|(f, w)| {
            let (start, end) = (
                w.first().copied().unwrap_or(0),
                w.get(1).copied().unwrap_or(0),
            );
            if end.saturating_sub(start) != 3 {
                return Err(invalid(
                    label,
                    &field,
                    format!(
                        "face {f} has {} vertices, expected a triangle",
                        end.saturating_sub(start)
                    ),
                ));
            }
            let mut tri = [0u32; 3];
            for (slot, j) in tri.iter_mut().zip(start..end) {
                let v = items.get(j).unwrap_or(f64::NAN);
                if !(v.fract() == 0.0 && v >= 0.0 && v < vertices as f64) {
                    return Err(invalid(
                        label,
                        &field,
                        format!("face {f} vertex index {v}, expected an index < {vertices}"),
                    ));
                }
                *slot = v as u32;
            }
            Ok(tri)
        })
        .collect()
}

/// Applies a 4x4 rigid transform (e.g. ScanNet's axis alignment) to mesh vertices.
pub fn align_mesh(mesh: &mut Mesh, a: &Mat4) {
    let moved: Vec<[f32; 3]> = mesh
        .vertices
        .iter()
        .map(|v| {
            let p = v.map(f64::from);
            std::array::from_fn(|i| {
                (a[i][0] * p[0] + a[i][1] * p[1] + a[i][2] * p[2] + a[i][3]) as f32
            })
        })
        .collect();
    mesh.vertices = moved.into();
}

/// The files of a NumPy vertex export (`<prefix>_vert_all.npy` and optional
/// `_sem_label_all.npy`, `_ins_label_all.npy`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NpyMeshFiles {
    pub vertices: PathBuf,
    pub semantic: Option<PathBuf>,
    pub instances: Option<PathBuf>,
}

/// Resolves a directory holding exactly one `*_vert_all.npy`, or a prefix
/// (`.../scene0000_00` or `.../scene0000_00_vert_all.npy`).
pub fn find_npy_mesh(dir_or_prefix: impl AsRef<Path>) -> Result<NpyMeshFiles> {
    let given = dir_or_prefix.as_ref();
    let prefix = if given.is_dir() {
        let found: Vec<PathBuf> = list_dir(given)?
            .into_iter()
            .filter(|p| p.to_string_lossy().ends_with("_vert_all.npy"))
            .collect();
        match found.as_slice() {
            [one] => strip_suffix(one, "_vert_all.npy"),
            [] => {
                return Err(missing(
                    &show(given),
                    "a `*_vert_all.npy` file",
                    "one vertex array in the directory",
                ))
            }
            _ => {
                return Err(invalid(
                    &show(given),
                    "`*_vert_all.npy`",
                    format!("{} candidates; pass the prefix instead", found.len()),
                ))
            }
        }
    } else {
        strip_suffix(given, "_vert_all.npy")
    };
    let with = |suffix: &str| PathBuf::from(format!("{}{suffix}", prefix.display()));
    let vertices = with("_vert_all.npy");
    if !vertices.is_file() {
        return Err(missing(
            &show(&vertices),
            "file",
            "a float (N, 6) xyz rgb vertex array",
        ));
    }
    let optional = |p: PathBuf| p.is_file().then_some(p);
    Ok(NpyMeshFiles {
        vertices,
        semantic: optional(with("_sem_label_all.npy")),
        instances: optional(with("_ins_label_all.npy")),
    })
}

fn strip_suffix(path: &Path, suffix: &str) -> PathBuf {
    let s = path.to_string_lossy();
    PathBuf::from(s.strip_suffix(suffix).unwrap_or(&s).to_string())
}

/// Reads ScanNet vertices from NumPy arrays: `*_vert_all.npy` float (N, 6) x y z r g b
/// with colours 0..255 (or (N, 3) without colours), and when present
/// `*_sem_label_all.npy` (NYU40 ids) and `*_ins_label_all.npy`, integer (N,).
pub fn read_scannet_npy(dir_or_prefix: impl AsRef<Path>) -> Result<(Mesh, MeshReport)> {
    let files = find_npy_mesh(dir_or_prefix)?;
    let label = show(&files.vertices);
    let verts = read_npy(&files.vertices)?;
    let (n, cols) = match (verts.shape.as_slice(), verts.dtype().is_float()) {
        ([n, c @ (3 | 6)], true) => (*n, *c),
        _ => {
            return Err(invalid(
                &label,
                "array",
                format!(
                    "shape {:?} dtype {}, expected float (N, 6) x y z r g b or (N, 3)",
                    verts.shape,
                    verts.dtype().code()
                ),
            ))
        }
    };
    let flat = verts.to_f64_vec();
    let mut vertices = Vec::with_capacity(n);
    let mut colors = Vec::with_capacity(if cols == 6 { n } else { 0 });
    for (i, row) in flat.chunks_exact(cols).enumerate() {
        let xyz: [f32; 3] = std::array::from_fn(|k| row.get(k).copied().unwrap_or(f64::NAN) as f32);
        if let Some(k) = xyz.iter().position(|v| !v.is_finite()) {
            return Err(crate::error::SceneError::NonFinite {
                path: label.clone(),
                field: format!("column {k} (x y z)"),
                index: i,
                value: profuse_formats::format_float(row.get(k).copied().unwrap_or(f64::NAN)),
            });
        }
        vertices.push(xyz);
        if cols == 6 {
            colors.push(rgb_byte_row(row, i, &label)?);
        }
    }
    let labels = optional_labels(files.semantic.as_deref(), n)?;
    let instances = optional_labels(files.instances.as_deref(), n)?;
    let file = files
        .vertices
        .file_name()
        .map(|f| f.to_string_lossy().into_owned())
        .unwrap_or_default();
    let mesh = Mesh {
        vertices: vertices.into(),
        colors: (cols == 6).then(|| colors.into()),
        faces: None,
        labels: labels.map(Into::into),
        instances: instances.map(Into::into),
        extra: BTreeMap::from([
            ("label_space".to_string(), NYU40_SPACE.to_string()),
            ("source".to_string(), format!("scannet_npy:{file}")),
        ]),
    };
    let report = MeshReport::of(&mesh);
    Ok((mesh, report))
}

/// Colour columns 3..6 of a row, 0..255 floats rounded to bytes.
fn rgb_byte_row(row: &[f64], vertex: usize, label: &str) -> Result<[u8; 3]> {
    let mut rgb = [0u8; 3];
    for (k, slot) in rgb.iter_mut().enumerate() {
        let v = row.get(3 + k).copied().unwrap_or(f64::NAN);
        if !(0.0..=255.0).contains(&v) {
            return Err(invalid(
                label,
                format!("column {} (r g b)", 3 + k),
                format!("vertex {vertex} has {v}, expected a colour in 0..=255"),
            ));
        }
        *slot = v.round() as u8;
    }
    Ok(rgb)
}

fn optional_labels(path: Option<&Path>, n: usize) -> Result<Option<Vec<u32>>> {
    let Some(path) = path else { return Ok(None) };
    let label = show(path);
    let array: NpyArray = read_npy(path)?;
    if array.shape != [n] || array.dtype().is_float() {
        return Err(invalid(
            &label,
            "array",
            format!(
                "shape {:?} dtype {}, expected an integer array of shape [{n}] (one per vertex)",
                array.shape,
                array.dtype().code()
            ),
        ));
    }
    array
        .to_u32_vec()
        .map(Some)
        .map_err(|e| invalid(&label, "labels", e.to_string()))
}
