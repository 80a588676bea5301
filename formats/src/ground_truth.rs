//! Typed readers of the JSON ground-truth files of a scene directory (`gt/`, SPEC.md §6.1):
//! `gt/scene.json` (the scene description a synthetic scene was made from) and
//! `gt/mask_objects.json` (the true object of every global mask).
//!
//! They live here, not in the scene generator, so that evaluators read ground truth
//! without depending on the generator (and its geometry library): the generator writes
//! these files, everything else reads them through this module. Only the fields a reader
//! uses are typed; other fields are ignored, so the generator may add fields without a
//! version change. The binary ground truth (`gt/mesh.safetensors`, `gt/views.safetensors`)
//! are ordinary file kinds (§4.12, §4.13).

use std::path::Path;

use serde::Deserialize;

use crate::label_space::{nyu40_name, NYU40_SPACE};

/// `format` of `gt/scene.json`.
pub const SCENE_FORMAT: &str = "synth.scene";
/// The `version` of `gt/scene.json` this reader knows.
pub const SCENE_VERSION: u32 = 1;

/// Why a ground-truth file could not be read; every variant names the file, content
/// errors the field and what was expected. [`GtError::code`] is shared with the Python
/// reader (`profuse_formats.GtError.code`).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GtError {
    /// The file could not be read.
    #[error("{path}: {action}: {source}")]
    Io {
        /// The path.
        path: String,
        /// What was attempted.
        action: &'static str,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// The text is not JSON of the expected structure (a field missing or of the wrong type).
    #[error("{path}: not a valid {expected}: {source}")]
    Json {
        /// The path.
        path: String,
        /// The schema expected.
        expected: &'static str,
        /// The parser's error (with line and column).
        #[source]
        source: serde_json::Error,
    },
    /// A field parses but its value is not allowed.
    #[error("{path}: `{field}`: {detail}")]
    Invalid {
        /// The path.
        path: String,
        /// The field, e.g. `objects[3].index`.
        field: String,
        /// What is wrong and what was expected.
        detail: String,
    },
}

impl GtError {
    /// `"io"`, `"json"` or `"invalid"`.
    pub fn code(&self) -> &'static str {
        match self {
            GtError::Io { .. } => "io",
            GtError::Json { .. } => "json",
            GtError::Invalid { .. } => "invalid",
        }
    }

    /// The offending field (`None` for I/O and JSON-structure errors).
    pub fn field(&self) -> Option<&str> {
        match self {
            GtError::Invalid { field, .. } => Some(field),
            _ => None,
        }
    }
}

fn invalid(path: &str, field: impl Into<String>, detail: impl Into<String>) -> GtError {
    GtError::Invalid {
        path: path.to_string(),
        field: field.into(),
        detail: detail.into(),
    }
}

fn read_text(path: &Path) -> Result<String, GtError> {
    std::fs::read_to_string(path).map_err(|source| GtError::Io {
        path: path.display().to_string(),
        action: "cannot read",
        source,
    })
}

/// The parts of `gt/scene.json` a reader outside the generator uses.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneTruth {
    /// The label space of the class ids (`nyu40` for synth scenes).
    pub label_space: String,
    /// The room's inner box `[−x/2, x/2] × [−y/2, y/2] × [0, z]` (`room.size`), metres.
    pub room_size: [f64; 3],
    /// Every object, index = object id of `gt/views.safetensors` (room surfaces first).
    pub objects: Vec<SceneObject>,
}

/// One object of [`SceneTruth`].
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct SceneObject {
    /// Object id (= position in `objects`); mesh instance = index + 1.
    pub index: u32,
    /// Unique name, e.g. `floor`, `chair_1`.
    pub name: String,
    /// Class id in the label space.
    pub class_id: u32,
    /// Class name (the label space's name of `class_id`).
    pub class_name: String,
    /// Whether this is a room surface (floor, ceiling, wall).
    pub room: bool,
}

#[derive(Deserialize)]
struct SceneJson {
    format: String,
    version: u32,
    label_space: String,
    room: RoomJson,
    objects: Vec<SceneObject>,
}

#[derive(Deserialize)]
struct RoomJson {
    size: [f64; 3],
}

impl SceneTruth {
    /// Reads and validates `gt/scene.json`.
    pub fn read(path: impl AsRef<Path>) -> Result<SceneTruth, GtError> {
        let path = path.as_ref();
        SceneTruth::parse(&read_text(path)?, &path.display().to_string())
    }

    /// Parses and validates the text of a `gt/scene.json`; `shown` names it in errors.
    ///
    /// Rules: `format` is `synth.scene`, `version` 1, `room.size` finite and positive,
    /// `objects[i].index == i`, names non-empty and distinct, and in the `nyu40` label
    /// space every `class_id` is in 1..=40 with its NYU40 `class_name`.
    pub fn parse(text: &str, shown: &str) -> Result<SceneTruth, GtError> {
        let json: SceneJson = serde_json::from_str(text).map_err(|source| GtError::Json {
            path: shown.to_string(),
            expected: "gt/scene.json ({format, version, label_space, room: {size}, \
                       objects: [{index, name, class_id, class_name, room}]})",
            source,
        })?;
        if json.format != SCENE_FORMAT {
            return Err(invalid(
                shown,
                "format",
                format!("{:?}, expected {SCENE_FORMAT:?}", json.format),
            ));
        }
        if json.version != SCENE_VERSION {
            return Err(invalid(
                shown,
                "version",
                format!("{}, expected {SCENE_VERSION}", json.version),
            ));
        }
        if !json.room.size.iter().all(|v| v.is_finite() && *v > 0.0) {
            return Err(invalid(
                shown,
                "room.size",
                format!("{:?}, expected three finite lengths > 0", json.room.size),
            ));
        }
        let mut names = std::collections::BTreeSet::new();
        for (i, o) in json.objects.iter().enumerate() {
            if o.index as usize != i {
                return Err(invalid(
                    shown,
                    format!("objects[{i}].index"),
                    format!("{}, expected {i} (objects are listed by index)", o.index),
                ));
            }
            if o.name.is_empty() || !names.insert(o.name.as_str()) {
                return Err(invalid(
                    shown,
                    format!("objects[{i}].name"),
                    format!(
                        "{:?}, expected a non-empty name no other object has",
                        o.name
                    ),
                ));
            }
            if json.label_space == NYU40_SPACE {
                let Some(name) = nyu40_name(o.class_id) else {
                    return Err(invalid(
                        shown,
                        format!("objects[{i}].class_id"),
                        format!("{}, expected a NYU40 id in 1..=40", o.class_id),
                    ));
                };
                if o.class_name != name {
                    return Err(invalid(
                        shown,
                        format!("objects[{i}].class_name"),
                        format!(
                            "{:?}, expected {name:?} (the NYU40 name of class {})",
                            o.class_name, o.class_id
                        ),
                    ));
                }
            }
        }
        Ok(SceneTruth {
            label_space: json.label_space,
            room_size: json.room.size,
            objects: json.objects,
        })
    }

    /// The class id of every object, index = object id.
    pub fn object_classes(&self) -> Vec<u32> {
        self.objects.iter().map(|o| o.class_id).collect()
    }
}

/// `gt/mask_objects.json`: the dominant ground-truth object of every global mask of
/// `masks.safetensors`.
#[derive(Debug, Clone, PartialEq)]
pub struct MaskObjects {
    /// Entry `i` is the object of global mask `i`; `None` for a mask on no object.
    pub objects: Vec<Option<u32>>,
}

#[derive(Deserialize)]
struct MaskObjectsJson {
    num_masks: usize,
    masks: Vec<MaskObjectJson>,
}

#[derive(Deserialize)]
struct MaskObjectJson {
    id: usize,
    object: Option<u32>,
}

impl MaskObjects {
    /// Reads and validates `gt/mask_objects.json`.
    pub fn read(path: impl AsRef<Path>) -> Result<MaskObjects, GtError> {
        let path = path.as_ref();
        MaskObjects::parse(&read_text(path)?, &path.display().to_string())
    }

    /// Parses and validates the text of a `gt/mask_objects.json`; `shown` names it in
    /// errors. Rules: `masks` has `num_masks` entries whose `id`s are each of
    /// `0..num_masks` once (in any order), and no `object` is 4294967295 (reserved for
    /// "no object" in the in-memory arrays of evaluators; the file says `null`).
    pub fn parse(text: &str, shown: &str) -> Result<MaskObjects, GtError> {
        let json: MaskObjectsJson = serde_json::from_str(text).map_err(|source| GtError::Json {
            path: shown.to_string(),
            expected: "gt/mask_objects.json ({num_masks, masks: [{id, object}]})",
            source,
        })?;
        if json.masks.len() != json.num_masks {
            return Err(invalid(
                shown,
                "masks",
                format!(
                    "{} entries, expected num_masks = {}",
                    json.masks.len(),
                    json.num_masks
                ),
            ));
        }
        let mut objects = vec![None; json.num_masks];
        let mut seen = vec![false; json.num_masks];
        for (k, m) in json.masks.iter().enumerate() {
            if m.id >= json.num_masks || seen[m.id] {
                return Err(invalid(
                    shown,
                    format!("masks[{k}].id"),
                    format!("{}, expected each of 0..{} once", m.id, json.num_masks),
                ));
            }
            if m.object == Some(u32::MAX) {
                return Err(invalid(
                    shown,
                    format!("masks[{k}].object"),
                    format!("{} is reserved, expected an object index or null", u32::MAX),
                ));
            }
            seen[m.id] = true;
            objects[m.id] = m.object;
        }
        Ok(MaskObjects { objects })
    }
}

/// A golden vector of a ground-truth file: its path under `formats/vectors/`, its text,
/// and the verdict every reader must reach (`None` = valid, else the error code and field).
#[derive(Debug, Clone)]
pub struct GtVector {
    /// Path relative to `formats/vectors/`, e.g. `gt/valid/scene.json`.
    pub name: String,
    /// The file's text.
    pub text: String,
    /// `None` for a valid file, else (code, field).
    pub error: Option<(&'static str, Option<&'static str>)>,
}

/// The golden vectors of the ground-truth files (written by the `write_vectors` example
/// into `formats/vectors/gt/`, read by both implementations' tests).
pub fn gt_vectors() -> Vec<GtVector> {
    let object = |i: u32, name: &str, class: u32, room: bool| {
        serde_json::json!({
            "index": i, "name": name, "class_id": class,
            "class_name": nyu40_name(class).unwrap_or("?"), "room": room,
            // Fields the readers ignore, as synth writes them.
            "shape": {"kind": "ball", "radius": 0.5}, "yaw": 0.0
        })
    };
    let scene = |objects: serde_json::Value, version: u32| {
        serde_json::json!({
            "format": SCENE_FORMAT, "version": version, "generator": "profuse vectors",
            "preset": "demo", "seed": 0, "label_space": NYU40_SPACE,
            "room": {"size": [6.0, 5.0, 2.8], "slab_thickness": 0.2},
            "objects": objects,
        })
    };
    let good_objects = serde_json::json!([
        object(0, "floor", 2, true),
        object(1, "chair_1", 5, false),
        object(2, "table_1", 7, false),
    ]);
    let bad_class = serde_json::json!([object(0, "floor", 2, true), object(1, "thing", 41, false)]);
    let masks = |entries: serde_json::Value, n: usize| serde_json::json!({"num_masks": n, "masks": entries});
    let mask = |id: usize, object: Option<u32>| serde_json::json!({"id": id, "view": 0, "local": id, "object": object, "purity": 1.0});
    let text = |v: serde_json::Value| serde_json::to_string_pretty(&v).unwrap_or_default() + "\n";
    vec![
        GtVector {
            name: "gt/valid/scene.json".into(),
            text: text(scene(good_objects.clone(), SCENE_VERSION)),
            error: None,
        },
        GtVector {
            name: "gt/valid/mask_objects.json".into(),
            text: text(masks(
                serde_json::json!([mask(1, None), mask(0, Some(2)), mask(2, Some(1))]),
                3,
            )),
            error: None,
        },
        GtVector {
            name: "gt/invalid/scene_version.json".into(),
            text: text(scene(good_objects, 2)),
            error: Some(("invalid", Some("version"))),
        },
        GtVector {
            name: "gt/invalid/scene_class_id.json".into(),
            text: text(scene(bad_class, SCENE_VERSION)),
            error: Some(("invalid", Some("objects[1].class_id"))),
        },
        GtVector {
            name: "gt/invalid/scene_no_objects.json".into(),
            text: "{\"format\": \"synth.scene\", \"version\": 1}\n".into(),
            error: Some(("json", None)),
        },
        GtVector {
            name: "gt/invalid/mask_objects_duplicate_id.json".into(),
            text: text(masks(
                serde_json::json!([mask(0, Some(1)), mask(0, None)]),
                2,
            )),
            error: Some(("invalid", Some("masks[1].id"))),
        },
    ]
}

/// `formats/vectors/gt/expected.json`: for every vector, `{"valid": true}` or
/// `{"valid": false, "code": ..., "field": ...}`.
pub fn gt_expected_json(vectors: &[GtVector]) -> serde_json::Value {
    let mut map = serde_json::Map::new();
    for v in vectors {
        let entry = match v.error {
            None => serde_json::json!({"valid": true}),
            Some((code, field)) => {
                serde_json::json!({"valid": false, "code": code, "field": field})
            }
        };
        map.insert(v.name.clone(), entry);
    }
    serde_json::Value::Object(map)
}

/// Reads a ground-truth vector by its file name (`scene*` or `mask_objects*`), for the
/// vector tests of both implementations.
pub fn read_gt_vector(path: &Path) -> Result<(), GtError> {
    let is_scene = path
        .file_name()
        .is_some_and(|n| n.to_string_lossy().starts_with("scene"));
    if is_scene {
        SceneTruth::read(path).map(|_| ())
    } else {
        MaskObjects::read(path).map(|_| ())
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn every_vector_gets_its_verdict() {
        for v in gt_vectors() {
            let shown = v.name.as_str();
            let got = if v.name.contains("scene") {
                SceneTruth::parse(&v.text, shown).map(|_| ())
            } else {
                MaskObjects::parse(&v.text, shown).map(|_| ())
            };
            match (got, v.error) {
                (Ok(()), None) => {}
                (Err(e), Some((code, field))) => {
                    assert_eq!((e.code(), e.field()), (code, field), "{shown}: {e}")
                }
                (got, want) => panic!("{shown}: got {got:?}, expected {want:?}"),
            }
        }
    }

    #[test]
    fn valid_files_read_back_their_values() {
        let v = gt_vectors();
        let scene = SceneTruth::parse(&v[0].text, "s").unwrap();
        assert_eq!(scene.object_classes(), vec![2, 5, 7]);
        assert_eq!(scene.room_size, [6.0, 5.0, 2.8]);
        assert_eq!(scene.objects[1].name, "chair_1");
        let masks = MaskObjects::parse(&v[1].text, "m").unwrap();
        assert_eq!(masks.objects, vec![Some(2), None, Some(1)]);
    }

    #[test]
    fn each_rule_is_enforced() {
        let good = &gt_vectors()[0].text;
        let edit = |from: &str, to: &str| {
            assert!(good.contains(from), "{from}");
            SceneTruth::parse(&good.replacen(from, to, 1), "s")
                .unwrap_err()
                .field()
                .map(str::to_string)
        };
        assert_eq!(edit("synth.scene", "other"), Some("format".into()));
        assert_eq!(edit("6.0", "-6.0"), Some("room.size".into()));
        assert_eq!(
            edit("\"index\": 1", "\"index\": 2"),
            Some("objects[1].index".into())
        );
        assert_eq!(
            edit("\"chair_1\"", "\"floor\""),
            Some("objects[1].name".into())
        );
        assert_eq!(
            edit("\"class_name\": \"chair\"", "\"class_name\": \"sofa\""),
            Some("objects[1].class_name".into())
        );
        let m = |text: &str| {
            MaskObjects::parse(text, "m")
                .unwrap_err()
                .field()
                .map(str::to_string)
        };
        assert_eq!(
            m(r#"{"num_masks": 2, "masks": [{"id": 0, "object": 1}]}"#),
            Some("masks".into())
        );
        assert_eq!(
            m(r#"{"num_masks": 1, "masks": [{"id": 0, "object": 4294967295}]}"#),
            Some("masks[0].object".into())
        );
    }
}
