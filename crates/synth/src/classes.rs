//! The classes the generator builds, as ids of the NYU40 label space
//! ([`profuse_formats::label_space`]) so the ScanNet protocol works on synthetic scenes.

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

#[cfg(test)]
mod tests {
    use super::*;
    use profuse_formats::label_space::nyu40_name as class_name;

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
