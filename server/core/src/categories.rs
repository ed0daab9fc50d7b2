//! The 41 semantic categories of HPointLoc (Matterport3D's mpcat40 set: index 0 is "void").

/// Category names indexed by category id, as HPointLoc labels instances.
pub const CATEGORIES: [&str; 41] = [
    "void",
    "wall",
    "floor",
    "chair",
    "door",
    "table",
    "picture",
    "cabinet",
    "cushion",
    "window",
    "sofa",
    "bed",
    "curtain",
    "chest_of_drawers",
    "plant",
    "sink",
    "stairs",
    "ceiling",
    "toilet",
    "stool",
    "towel",
    "mirror",
    "tv_monitor",
    "shower",
    "column",
    "bathtub",
    "counter",
    "fireplace",
    "lighting",
    "beam",
    "railing",
    "shelving",
    "blinds",
    "gym_equipment",
    "seating",
    "board_panel",
    "furniture",
    "appliances",
    "clothes",
    "objects",
    "misc",
];

/// The id of a category name, if it is one of [`CATEGORIES`].
pub fn category_id(name: &str) -> Option<u8> {
    CATEGORIES.iter().position(|c| *c == name).map(|i| i as u8)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lookup() {
        assert_eq!(category_id("wall"), Some(1));
        assert_eq!(category_id("misc"), Some(40));
        assert_eq!(category_id("spaceship"), None);
        assert_eq!(CATEGORIES.len(), 41);
    }
}
