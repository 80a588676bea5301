//! Label spaces: the class vocabularies files refer to by name (`label_space = nyu40` in
//! prompts, mesh and vertex_labels metadata, SPEC.md §4) and the names that go with them.
//!
//! They live with the formats rather than with a stage or the scene generator because every
//! layer needs them: the generator labels its meshes in NYU40, the transfer writes NYU40
//! ids, the ScanNet protocol scores the 19/15/10-class subsets, and the query stage and the
//! generator must agree on the LERF canonical negatives. One definition keeps them equal.

/// The `label_space` metadata value of NYU40 class ids.
pub const NYU40_SPACE: &str = "nyu40";

/// The 40 NYU40 class names (ScanNet's `nyu40class`, spaces removed); class id `i`
/// (1-based) is `NYU40[i - 1]`, 0 is unannotated (SPEC.md §3.4).
pub const NYU40: [&str; 40] = [
    "wall",
    "floor",
    "cabinet",
    "bed",
    "chair",
    "sofa",
    "table",
    "door",
    "window",
    "bookshelf",
    "picture",
    "counter",
    "blinds",
    "desk",
    "shelves",
    "curtain",
    "dresser",
    "pillow",
    "mirror",
    "floormat",
    "clothes",
    "ceiling",
    "books",
    "refrigerator",
    "television",
    "paper",
    "towel",
    "showercurtain",
    "box",
    "whiteboard",
    "person",
    "nightstand",
    "toilet",
    "sink",
    "lamp",
    "bathtub",
    "bag",
    "otherstructure",
    "otherfurniture",
    "otherprop",
];

/// The NYU40 name of a class id, `None` outside 1..=40.
///
/// ```
/// use profuse_formats::label_space::nyu40_name;
/// assert_eq!(nyu40_name(1), Some("wall"));
/// assert_eq!((nyu40_name(0), nyu40_name(41)), (None, None));
/// ```
pub fn nyu40_name(id: u32) -> Option<&'static str> {
    id.checked_sub(1)
        .and_then(|i| NYU40.get(i as usize))
        .copied()
}

/// The 19 NYU40 ids of OpenGaussian's ScanNet protocol (paper §4.3, Table 2).
pub const SCANNET_19: [u32; 19] = [
    1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 24, 28, 33, 34, 36,
];
/// The protocol's 15-class subset.
pub const SCANNET_15: [u32; 15] = [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 12, 14, 16, 33, 34];
/// The protocol's 10-class subset.
pub const SCANNET_10: [u32; 10] = [1, 2, 4, 5, 6, 7, 8, 9, 10, 33];

/// The canonical negative prompts of the LERF relevancy score (LERF §3.4, reused by
/// LangSplat and ProFuse): a query's relevancy is its worst pairwise softmax against these.
/// Prompts files list them like any prompt; the query stage recognises them by name, and
/// a generator must not use them as object names.
pub const CANONICAL_NEGATIVES: [&str; 4] = ["object", "things", "stuff", "texture"];

/// The file stem a prompt's outputs are named by (LERF-style predicted masks
/// `PRED_DIR/<frame_stem>/<stem>.png`, SPEC.md §6, and the query stage's per-prompt files):
/// the prompt text with `/`, `\` and control characters (NUL included) replaced by `_`,
/// so a prompt can never name a path outside its folder. What to do with the names this
/// leaves unusable (empty, `.`, `..`) is the caller's rule.
///
/// ```
/// use profuse_formats::label_space::prompt_file_stem;
/// assert_eq!(prompt_file_stem("a/b\\c\0d"), "a_b_c_d");
/// ```
pub fn prompt_file_stem(prompt: &str) -> String {
    prompt
        .chars()
        .map(|c| {
            if matches!(c, '/' | '\\') || c.is_control() {
                '_'
            } else {
                c
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn class_sets_are_nested_ascending_nyu40_ids() {
        for set in [&SCANNET_19[..], &SCANNET_15, &SCANNET_10] {
            assert!(set.windows(2).all(|w| w[0] < w[1]));
            assert!(set.iter().all(|&id| nyu40_name(id).is_some()));
        }
        assert!(SCANNET_15.iter().all(|id| SCANNET_19.contains(id)));
        assert!(SCANNET_10.iter().all(|id| SCANNET_15.contains(id)));
        // The paper's table names these classes; spot-check the ids against the names.
        let names: Vec<_> = SCANNET_10.iter().filter_map(|&i| nyu40_name(i)).collect();
        assert_eq!(
            names,
            [
                "wall",
                "floor",
                "bed",
                "chair",
                "sofa",
                "table",
                "door",
                "window",
                "bookshelf",
                "toilet"
            ]
        );
    }

    #[test]
    fn names_are_distinct_and_negatives_are_not_classes() {
        let mut sorted = NYU40.to_vec();
        sorted.sort_unstable();
        sorted.dedup();
        assert_eq!(sorted.len(), 40);
        assert!(CANONICAL_NEGATIVES.iter().all(|n| !NYU40.contains(n)));
    }

    #[test]
    fn file_stems_replace_separators_and_controls_only() {
        assert_eq!(prompt_file_stem("red mug"), "red mug");
        assert_eq!(prompt_file_stem("../x\n"), ".._x_");
        assert_eq!(prompt_file_stem(""), "");
    }
}
