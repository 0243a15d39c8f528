//! Hostile and careless input to the map format (issue 12): maps crafted with correct
//! checksums (`common::craft`) whose layout is valid but whose numbers are absurd, and paths
//! that are not regular files. Each must be refused, or handled, in bounded memory and time.

mod common;

use common::{craft, craft_level, craft_level_points, craft_metadata, craft_points};
use sfpmap::format::Map;

#[test]
fn crafted_map_opens_and_verifies() {
    let bytes = craft(
        &craft_metadata(vec![craft_level(0, 8, 4)]),
        &[
            craft_points(3),
            craft_level_points(0, &[0, 2]),
            common::Crafted::raw(
                sfpmap::format::SectionKind::LevelDescShort,
                0,
                sfpmap::format::Dtype::F16,
                2,
                4,
                vec![0; 16],
            ),
        ],
    );
    let map = Map::from_bytes(&bytes).unwrap();
    map.verify().unwrap();
    assert_eq!(map.level(0).unwrap().len(), 2);
}
