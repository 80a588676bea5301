//! The NYU40 label space used by ScanNet, so the ScanNet protocol works on synthetic
//! scenes, and the classes the generator builds.

/// The 40 NYU40 class names; class id `i` (1-based) is `NYU40[i - 1]`.
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

/// NYU40 id of walls.
pub const WALL: u32 = 1;
/// NYU40 id of the floor.
pub const FLOOR: u32 = 2;
/// NYU40 id of cabinets (a box).
pub const CABINET: u32 = 3;
/// NYU40 id of beds (a large low box).
pub const BED: u32 = 4;
/// NYU40 id of chairs (an L-shaped triangle mesh: seat + back).
pub const CHAIR: u32 = 5;
/// NYU40 id of sofas (a capsule lying along its local x axis).
pub const SOFA: u32 = 6;
/// NYU40 id of tables (an upright cylinder).
pub const TABLE: u32 = 7;
/// NYU40 id of bookshelves (a tall thin box).
pub const BOOKSHELF: u32 = 10;
/// NYU40 id of the ceiling.
pub const CEILING: u32 = 22;
/// NYU40 id of lamps (a ball).
pub const LAMP: u32 = 35;

/// The object classes placed on the floor, in a fixed order.
pub const FURNITURE: [u32; 7] = [CABINET, BED, CHAIR, SOFA, TABLE, BOOKSHELF, LAMP];

/// The room-surface classes.
pub const ROOM: [u32; 3] = [WALL, FLOOR, CEILING];

/// The NYU40 name of a class id, `None` outside 1..=40.
pub fn class_name(id: u32) -> Option<&'static str> {
    id.checked_sub(1)
        .and_then(|i| NYU40.get(i as usize))
        .copied()
}

/// The canonical negative prompts of the LERF relevancy score.
pub const CANONICAL_NEGATIVES: [&str; 4] = ["object", "things", "stuff", "texture"];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_match_names() {
        assert_eq!(class_name(WALL), Some("wall"));
        assert_eq!(class_name(FLOOR), Some("floor"));
        assert_eq!(class_name(CEILING), Some("ceiling"));
        assert_eq!(class_name(BOOKSHELF), Some("bookshelf"));
        assert_eq!(class_name(LAMP), Some("lamp"));
        assert_eq!(class_name(0), None);
        assert_eq!(class_name(41), None);
    }
}
