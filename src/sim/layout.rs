//! The built-in room: structure (floor, walls, ceiling, a partition with a doorway), the
//! robot's route, and furniture — a fixed layout for seed 0, a random one for other seeds.
//!
//! # Layout
//!
//! The free interior is `x ∈ [0, 10]`, `y ∈ [0, 12]`, `z ∈ [0, 3]` m. Floor, ceiling and the four
//! walls are 0.2 m thick boxes just outside it, so the room is closed: every ray from inside
//! hits something within 16 m (realistic indoors, and it makes every lidar ray return). A
//! 0.2 m partition at `y ∈ [6.9, 7.1]` splits it into a south room and a north room, with a
//! 1.6 m wide, 2.1 m high doorway at `x ∈ [4.2, 5.8]` (a lintel fills the wall above it).
//!
//! The route is a rectangle in each room (`[2, 8] × [2, 5]` south, `[2, 8] × [8.5, 10.5]`
//! north) joined by a corridor along `x = 5` through the doorway; see [`ROUTE_XY`].
//!
//! Seed-0 furniture (the "default scene"):
//!
//! | item | solids | where (m) |
//! |---|---|---|
//! | crate, with a smaller crate on top | 2 boxes | `[0.3, 1.1] × [0.3, 1.0] × [0, 0.8]`, `[0.4, 0.9]² × [0.8, 1.2]` |
//! | table | top slab + 4 legs | top `[3.5, 5.5] × [3.0, 4.0] × [0.72, 0.76]`, 6 cm legs |
//! | pillar | cylinder, floor to ceiling | centre (9.3, 3.5), r 0.25 |
//! | barrel | cylinder | centre (6.5, 0.7), r 0.35, h 0.9 |
//! | ball | sphere on the floor | centre (6.5, 3.6, 0.3), r 0.3 |
//! | ceiling lamp | cylinder hanging from the ceiling | centre (5.0, 3.5), r 0.3, z 2.6..3 |
//! | shelf | box | `[0.2, 3.0] × [11.4, 11.9] × [0, 2.0]` |
//! | crate | box | `[8.8, 9.7] × [7.3, 8.1] × [0, 0.6]` |
//! | pillar | cylinder, floor to ceiling | centre (3.5, 9.5), r 0.2 |
//! | bench | box | `[6.0, 7.5] × [7.3, 7.8] × [0, 0.45]` |
//!
//! Other seeds draw the same items with random sizes and positions (rejection sampling with a
//! [`ChaCha8Rng`] seeded from the seed); each item's footprint keeps
//! [`ROUTE_CLEARANCE_M`] + 0.15 m from the route, 0.1 m from other items and from the
//! partition, and 0.05 m from the outer walls. An item that finds no place in 400 tries is left
//! out.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::ROUTE_CLEARANCE_M;
use super::scene::Scene;
use super::solid::{Solid, intersect, slab};

/// Size of the free interior of [`Scene::room`] (metres); its lower corner is the origin.
pub const ROOM_SIZE_M: [f64; 3] = [10.0, 12.0, 3.0];
/// Thickness of the floor, ceiling, outer walls and partition (metres).
const WALL_M: f64 = 0.2;
const PARTITION_Y: (f64, f64) = (6.9, 7.1);
const DOOR_X: (f64, f64) = (4.2, 5.8);
const DOOR_HEIGHT_M: f64 = 2.1;

/// The route of [`Scene::room`]: a closed loop (the last waypoint joins the first) around the
/// south room, through the doorway, around the north room and back.
pub const ROUTE_XY: [[f64; 2]; 12] = [
    [2.0, 2.0],
    [8.0, 2.0],
    [8.0, 5.0],
    [5.0, 5.0],
    [5.0, 8.5],
    [8.0, 8.5],
    [8.0, 10.5],
    [2.0, 10.5],
    [2.0, 8.5],
    [5.0, 8.5],
    [5.0, 5.0],
    [2.0, 5.0],
];

/// Extra margin of furniture footprints beyond [`ROUTE_CLEARANCE_M`] from the route.
const ROUTE_MARGIN_M: f64 = 0.15;
const ITEM_GAP_M: f64 = 0.1;
const WALL_GAP_M: f64 = 0.05;
const PLACEMENT_TRIES: usize = 400;

impl Scene {
    /// The built-in room (see the [module docs](self) for the layout): about 10 m × 12 m × 3 m,
    /// closed by a floor, four walls and a ceiling, split by a partition with a doorway, and
    /// furnished with crates, a table, pillars, a barrel, a ball, a lamp, a shelf and a bench.
    /// Seed 0 is the fixed default layout; other seeds randomise the furniture's sizes and
    /// positions, never within [`ROUTE_CLEARANCE_M`] of the route.
    pub fn room(seed: u64) -> Scene {
        let mut solids = structure();
        let items = if seed == 0 { default_furniture() } else { random_furniture(seed) };
        solids.extend(items.into_iter().flat_map(|item| item.solids));
        Scene { solids, interior_min: [0.0; 3], interior_max: ROOM_SIZE_M, route_xy: ROUTE_XY.to_vec() }
    }
}

/// Floor, ceiling, outer walls and the partition with its doorway.
fn structure() -> Vec<Solid> {
    let [sx, sy, sz] = ROOM_SIZE_M;
    let w = WALL_M;
    let aabb = |min: [f64; 3], max: [f64; 3]| Solid::Aabb { min, max };
    let (py0, py1) = PARTITION_Y;
    let (dx0, dx1) = DOOR_X;
    vec![
        aabb([-w, -w, -w], [sx + w, sy + w, 0.0]),
        aabb([-w, -w, sz], [sx + w, sy + w, sz + w]),
        aabb([-w, -w, 0.0], [0.0, sy + w, sz]),
        aabb([sx, -w, 0.0], [sx + w, sy + w, sz]),
        aabb([0.0, -w, 0.0], [sx, 0.0, sz]),
        aabb([0.0, sy, 0.0], [sx, sy + w, sz]),
        aabb([0.0, py0, 0.0], [dx0, py1, sz]),
        aabb([dx1, py0, 0.0], [sx, py1, sz]),
        aabb([dx0, py0, DOOR_HEIGHT_M], [dx1, py1, sz]),
    ]
}

/// The floor-plan outline of an item, used to keep items apart and off the route.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Footprint {
    Rect { min: [f64; 2], max: [f64; 2] },
    Circle { centre: [f64; 2], radius: f64 },
}

#[derive(Debug, Clone, PartialEq)]
struct Item {
    footprint: Footprint,
    solids: Vec<Solid>,
}

fn block(x0: f64, y0: f64, w: f64, d: f64, z0: f64, z1: f64) -> Solid {
    Solid::Aabb { min: [x0, y0, z0], max: [x0 + w, y0 + d, z1] }
}

fn rect_item(x0: f64, y0: f64, w: f64, d: f64, h: f64) -> Item {
    Item {
        footprint: Footprint::Rect { min: [x0, y0], max: [x0 + w, y0 + d] },
        solids: vec![block(x0, y0, w, d, 0.0, h)],
    }
}

/// A crate of `size` (w, d, h) with a smaller crate of `top` (w, d, h) on it, inset by `inset`
/// = (x, y) from the bottom crate's lower corner.
fn stacked_crates(x0: f64, y0: f64, size: [f64; 3], top: [f64; 3], inset: [f64; 2]) -> Item {
    let [w, d, h] = size;
    let mut item = rect_item(x0, y0, w, d, h);
    item.solids.push(block(x0 + inset[0], y0 + inset[1], top[0], top[1], h, h + top[2]));
    item
}

/// A table: a 4 cm top slab at height `h` and four 6 cm square legs inset 5 cm from the corners.
fn table(x0: f64, y0: f64, w: f64, d: f64, h: f64) -> Item {
    const TOP: f64 = 0.04;
    const LEG: f64 = 0.06;
    const INSET: f64 = 0.05;
    let mut solids = vec![block(x0, y0, w, d, h - TOP, h)];
    for lx in [x0 + INSET, x0 + w - INSET - LEG] {
        for ly in [y0 + INSET, y0 + d - INSET - LEG] {
            solids.push(block(lx, ly, LEG, LEG, 0.0, h - TOP));
        }
    }
    Item { footprint: Footprint::Rect { min: [x0, y0], max: [x0 + w, y0 + d] }, solids }
}

fn cylinder(centre: [f64; 2], radius: f64, z_min: f64, z_max: f64) -> Item {
    Item {
        footprint: Footprint::Circle { centre, radius },
        solids: vec![Solid::Cylinder { centre_xy: centre, radius, z_min, z_max }],
    }
}

fn ball(centre: [f64; 2], radius: f64) -> Item {
    Item {
        footprint: Footprint::Circle { centre, radius },
        solids: vec![Solid::Sphere { centre: [centre[0], centre[1], radius], radius }],
    }
}

fn default_furniture() -> Vec<Item> {
    let ceiling = ROOM_SIZE_M[2];
    vec![
        stacked_crates(0.3, 0.3, [0.8, 0.7, 0.8], [0.5, 0.5, 0.4], [0.1, 0.1]),
        table(3.5, 3.0, 2.0, 1.0, 0.76),
        cylinder([9.3, 3.5], 0.25, 0.0, ceiling),
        cylinder([6.5, 0.7], 0.35, 0.0, 0.9),
        ball([6.5, 3.6], 0.3),
        cylinder([5.0, 3.5], 0.3, ceiling - 0.4, ceiling),
        rect_item(0.2, 11.4, 2.8, 0.5, 2.0),
        rect_item(8.8, 7.3, 0.9, 0.8, 0.6),
        cylinder([3.5, 9.5], 0.2, 0.0, ceiling),
        rect_item(6.0, 7.3, 1.5, 0.5, 0.45),
    ]
}

/// The furniture kinds, in drawing order, each with random sizes.
#[derive(Debug, Clone, Copy)]
enum Kind {
    StackedCrates,
    Table,
    Pillar,
    Barrel,
    Ball,
    Lamp,
    Shelf,
    Crate,
    Bench,
}

const CATALOGUE: [Kind; 10] = [
    Kind::StackedCrates,
    Kind::Table,
    Kind::Pillar,
    Kind::Barrel,
    Kind::Ball,
    Kind::Lamp,
    Kind::Shelf,
    Kind::Crate,
    Kind::Pillar,
    Kind::Bench,
];

fn uniform(rng: &mut impl Rng, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * rng.random::<f64>()
}

/// The item of `kind` with sizes drawn from `rng`, placed with its footprint's lower corner at
/// the origin (`Rect`) or its centre at the origin (`Circle`); [`place`] moves it.
fn draw_item(kind: Kind, rng: &mut impl Rng) -> Item {
    let ceiling = ROOM_SIZE_M[2];
    match kind {
        Kind::StackedCrates => {
            let (w, d, h) = (uniform(rng, 0.5, 1.0), uniform(rng, 0.5, 1.0), uniform(rng, 0.4, 0.9));
            let top = [w * uniform(rng, 0.5, 0.8), d * uniform(rng, 0.5, 0.8)];
            let inset = [uniform(rng, 0.0, w - top[0]), uniform(rng, 0.0, d - top[1])];
            let h2 = uniform(rng, 0.3, 0.5);
            stacked_crates(0.0, 0.0, [w, d, h], [top[0], top[1], h2], inset)
        }
        Kind::Table => {
            let (w, d, h) = (uniform(rng, 1.2, 2.0), uniform(rng, 0.7, 1.0), uniform(rng, 0.7, 0.8));
            table(0.0, 0.0, w, d, h)
        }
        Kind::Pillar => cylinder([0.0, 0.0], uniform(rng, 0.15, 0.3), 0.0, ceiling),
        Kind::Barrel => cylinder([0.0, 0.0], uniform(rng, 0.25, 0.4), 0.0, uniform(rng, 0.8, 1.0)),
        Kind::Ball => ball([0.0, 0.0], uniform(rng, 0.2, 0.35)),
        Kind::Lamp => {
            let drop = uniform(rng, 0.3, 0.6);
            cylinder([0.0, 0.0], uniform(rng, 0.2, 0.35), ceiling - drop, ceiling)
        }
        Kind::Shelf => {
            let (len, depth, h) = (uniform(rng, 1.5, 2.8), uniform(rng, 0.35, 0.5), uniform(rng, 1.6, 2.2));
            if rng.random::<bool>() {
                rect_item(0.0, 0.0, len, depth, h)
            } else {
                rect_item(0.0, 0.0, depth, len, h)
            }
        }
        Kind::Crate => {
            let (w, d, h) = (uniform(rng, 0.6, 1.0), uniform(rng, 0.6, 1.0), uniform(rng, 0.4, 0.8));
            rect_item(0.0, 0.0, w, d, h)
        }
        Kind::Bench => {
            let (len, depth, h) = (uniform(rng, 1.0, 1.6), uniform(rng, 0.4, 0.5), uniform(rng, 0.4, 0.5));
            if rng.random::<bool>() {
                rect_item(0.0, 0.0, len, depth, h)
            } else {
                rect_item(0.0, 0.0, depth, len, h)
            }
        }
    }
}

/// `item` moved by `(dx, dy)`.
fn place(item: &Item, dx: f64, dy: f64) -> Item {
    let footprint = match item.footprint {
        Footprint::Rect { min, max } => {
            Footprint::Rect { min: [min[0] + dx, min[1] + dy], max: [max[0] + dx, max[1] + dy] }
        }
        Footprint::Circle { centre, radius } => {
            Footprint::Circle { centre: [centre[0] + dx, centre[1] + dy], radius }
        }
    };
    let solids = item
        .solids
        .iter()
        .map(|s| match *s {
            Solid::Aabb { min, max } => Solid::Aabb {
                min: [min[0] + dx, min[1] + dy, min[2]],
                max: [max[0] + dx, max[1] + dy, max[2]],
            },
            Solid::Cylinder { centre_xy, radius, z_min, z_max } => {
                Solid::Cylinder { centre_xy: [centre_xy[0] + dx, centre_xy[1] + dy], radius, z_min, z_max }
            }
            Solid::Sphere { centre, radius } => {
                Solid::Sphere { centre: [centre[0] + dx, centre[1] + dy, centre[2]], radius }
            }
        })
        .collect();
    Item { footprint, solids }
}

fn random_furniture(seed: u64) -> Vec<Item> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (py0, py1) = PARTITION_Y;
    let partition = [
        Footprint::Rect { min: [0.0, py0], max: [DOOR_X.0, py1] },
        Footprint::Rect { min: [DOOR_X.1, py0], max: [ROOM_SIZE_M[0], py1] },
    ];
    let mut placed: Vec<Item> = Vec::new();
    for kind in CATALOGUE {
        let item = draw_item(kind, &mut rng);
        // The range of offsets that keeps the footprint WALL_GAP_M inside the outer walls.
        let (lo, hi) = match item.footprint {
            Footprint::Rect { min, max } => (min, max),
            Footprint::Circle { centre, radius } => {
                ([centre[0] - radius, centre[1] - radius], [centre[0] + radius, centre[1] + radius])
            }
        };
        let range = [0, 1].map(|i| (WALL_GAP_M - lo[i], ROOM_SIZE_M[i] - WALL_GAP_M - hi[i]));
        for _ in 0..PLACEMENT_TRIES {
            let dx = uniform(&mut rng, range[0].0, range[0].1);
            let dy = uniform(&mut rng, range[1].0, range[1].1);
            let candidate = place(&item, dx, dy);
            let fp = candidate.footprint;
            let fits = route_distance(&fp, &ROUTE_XY) >= ROUTE_CLEARANCE_M + ROUTE_MARGIN_M
                && partition.iter().all(|p| footprint_distance(&fp, p) >= ITEM_GAP_M)
                && placed.iter().all(|p| footprint_distance(&fp, &p.footprint) >= ITEM_GAP_M);
            if fits {
                placed.push(candidate);
                break;
            }
        }
    }
    placed
}

fn dist2(a: [f64; 2], b: [f64; 2]) -> f64 {
    let (dx, dy) = (a[0] - b[0], a[1] - b[1]);
    (dx * dx + dy * dy).sqrt()
}

fn point_rect_distance(p: [f64; 2], min: [f64; 2], max: [f64; 2]) -> f64 {
    let c = [p[0].clamp(min[0], max[0]), p[1].clamp(min[1], max[1])];
    dist2(p, c)
}

fn point_segment_distance(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let ab = [b[0] - a[0], b[1] - a[1]];
    let len2 = ab[0] * ab[0] + ab[1] * ab[1];
    let t = if len2 > 0.0 {
        (((p[0] - a[0]) * ab[0] + (p[1] - a[1]) * ab[1]) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    dist2(p, [a[0] + t * ab[0], a[1] + t * ab[1]])
}

/// Distance between a segment and a footprint (0 when they meet).
fn segment_distance(fp: &Footprint, a: [f64; 2], b: [f64; 2]) -> f64 {
    match *fp {
        Footprint::Circle { centre, radius } => (point_segment_distance(centre, a, b) - radius).max(0.0),
        Footprint::Rect { min, max } => {
            let d = [b[0] - a[0], b[1] - a[1]];
            let crosses = slab(a[0], d[0], min[0], max[0])
                .zip(slab(a[1], d[1], min[1], max[1]))
                .and_then(|(x, y)| intersect(x, y))
                .and_then(|iv| intersect(iv, (0.0, 1.0)))
                .is_some();
            if crosses {
                return 0.0;
            }
            let corners = [min, [max[0], min[1]], max, [min[0], max[1]]];
            corners
                .iter()
                .map(|&c| point_segment_distance(c, a, b))
                .chain([point_rect_distance(a, min, max), point_rect_distance(b, min, max)])
                .fold(f64::INFINITY, f64::min)
        }
    }
}

/// Distance from a footprint to a closed polyline (the last point joins the first).
pub(crate) fn route_distance(fp: &Footprint, route: &[[f64; 2]]) -> f64 {
    (0..route.len())
        .map(|i| segment_distance(fp, route[i], route[(i + 1) % route.len()]))
        .fold(f64::INFINITY, f64::min)
}

fn footprint_distance(a: &Footprint, b: &Footprint) -> f64 {
    match (*a, *b) {
        (Footprint::Rect { min: a0, max: a1 }, Footprint::Rect { min: b0, max: b1 }) => {
            let gap = |i: usize| (a0[i] - b1[i]).max(b0[i] - a1[i]).max(0.0);
            let (gx, gy) = (gap(0), gap(1));
            (gx * gx + gy * gy).sqrt()
        }
        (Footprint::Circle { centre, radius }, Footprint::Rect { min, max })
        | (Footprint::Rect { min, max }, Footprint::Circle { centre, radius }) => {
            (point_rect_distance(centre, min, max) - radius).max(0.0)
        }
        (Footprint::Circle { centre: c0, radius: r0 }, Footprint::Circle { centre: c1, radius: r1 }) => {
            (dist2(c0, c1) - r0 - r1).max(0.0)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn segment_rect_distance_cases() {
        let r = Footprint::Rect { min: [0.0, 0.0], max: [1.0, 1.0] };
        assert_eq!(segment_distance(&r, [-1.0, 0.5], [2.0, 0.5]), 0.0);
        assert_eq!(segment_distance(&r, [-1.0, 2.0], [2.0, 2.0]), 1.0);
        assert_eq!(segment_distance(&r, [3.0, 0.5], [3.0, 0.7]), 2.0);
        // A diagonal segment passing the corner (1, 1) at distance √2/2.
        assert!((segment_distance(&r, [2.0, 1.0], [1.0, 2.0]) - 0.5f64.sqrt()).abs() < 1e-12);
        let c = Footprint::Circle { centre: [0.0, 3.0], radius: 0.5 };
        assert_eq!(segment_distance(&c, [-1.0, 0.0], [1.0, 0.0]), 2.5);
        assert_eq!(footprint_distance(&r, &c), 1.5);
    }

    #[test]
    fn default_and_random_layouts_keep_items_apart_and_off_the_route() {
        for seed in 0..40 {
            let items = if seed == 0 { default_furniture() } else { random_furniture(seed) };
            assert!(items.len() >= 7, "seed {seed}: only {} items placed", items.len());
            for (i, a) in items.iter().enumerate() {
                assert!(route_distance(&a.footprint, &ROUTE_XY) >= ROUTE_CLEARANCE_M + 0.1, "seed {seed}");
                for b in &items[i + 1..] {
                    let lamp =
                        |it: &Item| matches!(it.solids[0], Solid::Cylinder { z_min, .. } if z_min > 2.0);
                    if !lamp(a) && !lamp(b) {
                        assert!(footprint_distance(&a.footprint, &b.footprint) > 0.0, "seed {seed}");
                    }
                }
            }
        }
    }

    #[test]
    fn seeds_give_fixed_or_different_layouts() {
        assert_eq!(Scene::room(0), Scene::room(0));
        assert_eq!(Scene::room(5), Scene::room(5));
        assert_ne!(Scene::room(0), Scene::room(1));
        assert_ne!(Scene::room(1), Scene::room(2));
        assert_eq!(Scene::room(0).solids.len(), 9 + 2 + 5 + 8);
    }
}
