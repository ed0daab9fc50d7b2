//! Procedural apartments made of axis-aligned boxes.
//!
//! Why boxes: indoor scenes are mostly planes meeting at right angles, a ray against an axis-aligned
//! box is a handful of instructions, and depth, normals and labels come out exact. That keeps the
//! renderer small and fast enough to make a Val-sized scene in seconds, while walls with door openings,
//! furniture of several kinds, pictures and windows give retrieval and matching real work to do.
//!
//! World frame as in HPointLoc/Habitat: y up, floor at y = 0; the apartment spans x in 0..width and
//! z in 0..depth.

use nalgebra::Vector3;
use pntr_core::categories::category_id;
use rand::seq::SliceRandom;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use crate::texture::{Material, Pattern, Rgb, TextureImage};
use std::sync::Arc;

/// One box of the scene. Faces are indexed `axis * 2 + (normal points to +axis) as usize`.
#[derive(Debug, Clone)]
pub struct SceneBox {
    /// Minimum corner, metres.
    pub min: Vector3<f32>,
    /// Maximum corner, metres.
    pub max: Vector3<f32>,
    /// Material index per face.
    pub faces: [u16; 6],
    /// Instance id (index into [`Scene::instance_categories`]); 0 is reserved for "nothing".
    pub instance: u32,
}

/// An axis-aligned rectangle of floor, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rect {
    /// Minimum x.
    pub x0: f32,
    /// Minimum z.
    pub z0: f32,
    /// Maximum x.
    pub x1: f32,
    /// Maximum z.
    pub z1: f32,
}

impl Rect {
    fn w(&self) -> f32 {
        self.x1 - self.x0
    }
    fn d(&self) -> f32 {
        self.z1 - self.z0
    }
    fn overlaps(&self, o: &Rect) -> bool {
        self.x0 < o.x1 && o.x0 < self.x1 && self.z0 < o.z1 && o.z0 < self.z1
    }
    fn inset(&self, m: f32) -> Rect {
        Rect {
            x0: self.x0 + m,
            z0: self.z0 + m,
            x1: self.x1 - m,
            z1: self.z1 - m,
        }
    }
    fn contains(&self, o: &Rect) -> bool {
        o.x0 >= self.x0 && o.x1 <= self.x1 && o.z0 >= self.z0 && o.z1 <= self.z1
    }
}

/// A door opening in a wall line.
#[derive(Debug, Clone, Copy)]
struct Door {
    /// True when the wall runs along x (constant z = `at`), false when it runs along z (constant x).
    along_x: bool,
    at: f32,
    a: f32,
    b: f32,
}

/// Height of door openings, metres.
pub const DOOR_HEIGHT_M: f32 = 2.1;
const DOOR_WIDTH_M: f32 = 0.9;
const WALL_HALF_M: f32 = 0.06;

/// A generated scene.
#[derive(Debug, Clone)]
pub struct Scene {
    /// The scene's name (folder name in the dataset).
    pub name: String,
    /// All geometry.
    pub boxes: Vec<SceneBox>,
    /// All materials, indexed by `SceneBox::faces`.
    pub materials: Vec<Material>,
    /// Category id of each instance id (index 0 = void).
    pub instance_categories: Vec<u8>,
    /// Rooms' floor rectangles.
    pub rooms: Vec<Rect>,
    /// Ceiling height, metres.
    pub ceiling_m: f32,
    /// Apartment size along x, metres.
    pub width_m: f32,
    /// Apartment size along z, metres.
    pub depth_m: f32,
    /// Directions toward the two scene lights (unit vectors).
    pub lights: [Vector3<f32>; 2],
}

impl Scene {
    /// Horizontal footprints of everything a robot (up to 1.8 m tall) bumps into: walls and
    /// furniture, not the floor, ceiling, rugs or pictures hanging above the body.
    pub fn obstacles(&self) -> Vec<Rect> {
        self.boxes
            .iter()
            .filter(|b| b.min.y < 1.8 && b.max.y > 0.05)
            .map(|b| Rect {
                x0: b.min.x,
                z0: b.min.z,
                x1: b.max.x,
                z1: b.max.z,
            })
            .collect()
    }

    /// Distance from (x, z) to the nearest obstacle footprint, or to the apartment's outer boundary;
    /// 0 inside an obstacle or outside the apartment.
    pub fn clearance(obstacles: &[Rect], width: f32, depth: f32, x: f32, z: f32) -> f32 {
        if x <= 0.0 || z <= 0.0 || x >= width || z >= depth {
            return 0.0;
        }
        let mut best = x.min(z).min(width - x).min(depth - z);
        for r in obstacles {
            let dx = (r.x0 - x).max(0.0).max(x - r.x1);
            let dz = (r.z0 - z).max(0.0).max(z - r.z1);
            let d = (dx * dx + dz * dz).sqrt();
            if d < best {
                best = d;
                if best == 0.0 {
                    break;
                }
            }
        }
        best
    }
}

/// Options for scene generation.
#[derive(Debug, Clone, Default)]
pub struct SceneOptions {
    /// Extra image textures to mix into the palettes (from `--textures DIR`).
    pub images: Vec<Arc<TextureImage>>,
}

struct Builder<'a> {
    rng: &'a mut ChaCha8Rng,
    boxes: Vec<SceneBox>,
    materials: Vec<Material>,
    cats: Vec<u8>,
    images: &'a [Arc<TextureImage>],
}

fn rgb(rng: &mut ChaCha8Rng, lo: f32, hi: f32) -> Rgb {
    [
        rng.gen_range(lo..hi),
        rng.gen_range(lo..hi),
        rng.gen_range(lo..hi),
    ]
}

fn tint(rng: &mut ChaCha8Rng, base: Rgb, amount: f32) -> Rgb {
    let mut c = base;
    for v in &mut c {
        *v = (*v + rng.gen_range(-amount..amount)).clamp(0.02, 0.98);
    }
    c
}

impl Builder<'_> {
    fn material(&mut self, m: Material) -> u16 {
        self.materials.push(m);
        (self.materials.len() - 1) as u16
    }

    fn instance(&mut self, category: &str) -> u32 {
        let id = category_id(category).expect("known category");
        self.cats.push(id);
        (self.cats.len() - 1) as u32
    }

    fn add(&mut self, min: Vector3<f32>, max: Vector3<f32>, mat: u16, inst: u32) {
        self.boxes.push(SceneBox {
            min,
            max,
            faces: [mat; 6],
            instance: inst,
        });
    }

    fn seed(&mut self) -> u32 {
        self.rng.gen()
    }

    fn wall_material(&mut self) -> u16 {
        let seed = self.seed();
        let r = &mut *self.rng;
        let a = rgb(r, 0.45, 0.95);
        let b = tint(r, a, 0.25);
        let pattern = match r.gen_range(0..8) {
            0 => Pattern::Plain,
            1 => Pattern::Stripes {
                period: r.gen_range(0.08..0.3),
                duty: r.gen_range(0.3..0.7),
                vertical: true,
            },
            2 => Pattern::Dots {
                spacing: r.gen_range(0.08..0.2),
                radius: r.gen_range(0.015..0.04),
            },
            3 => Pattern::Bricks {
                w: r.gen_range(0.2..0.3),
                h: r.gen_range(0.06..0.1),
            },
            4 => Pattern::Tiles {
                size: r.gen_range(0.1..0.3),
            },
            5 => Pattern::Noise {
                scale: r.gen_range(0.1..0.5),
            },
            6 => Pattern::Checker {
                size: r.gen_range(0.15..0.4),
            },
            _ => {
                if let Some(img) = self.images.choose(r).cloned() {
                    Pattern::Image {
                        image: img,
                        tile: r.gen_range(0.4..1.2),
                    }
                } else {
                    Pattern::Stripes {
                        period: r.gen_range(0.1..0.4),
                        duty: 0.5,
                        vertical: false,
                    }
                }
            }
        };
        let b = match pattern {
            Pattern::Dots { .. } | Pattern::Checker { .. } | Pattern::Stripes { .. } => {
                rgb(self.rng, 0.15, 0.85)
            }
            Pattern::Bricks { .. } | Pattern::Tiles { .. } => [0.85, 0.85, 0.82],
            _ => b,
        };
        self.material(Material::new(pattern, a, b, seed))
    }

    fn floor_material(&mut self) -> u16 {
        let seed = self.seed();
        let r = &mut *self.rng;
        let (pattern, a, b) = match r.gen_range(0..4) {
            0 => (
                Pattern::Wood {
                    ring: r.gen_range(0.02..0.06),
                },
                [0.55, 0.38, 0.22],
                [0.35, 0.22, 0.12],
            ),
            1 => (
                Pattern::Tiles {
                    size: r.gen_range(0.3..0.6),
                },
                rgb(r, 0.5, 0.9),
                [0.3, 0.3, 0.3],
            ),
            2 => (
                Pattern::Checker {
                    size: r.gen_range(0.25..0.5),
                },
                rgb(r, 0.6, 0.95),
                rgb(r, 0.1, 0.4),
            ),
            _ => {
                let a = rgb(r, 0.2, 0.6);
                let b = tint(r, a, 0.2);
                (Pattern::Noise { scale: 0.05 }, a, b)
            }
        };
        self.material(Material::new(pattern, a, b, seed))
    }

    fn ceiling_material(&mut self) -> u16 {
        let seed = self.seed();
        let a = rgb(self.rng, 0.85, 0.97);
        self.material(Material::new(
            Pattern::Noise { scale: 0.8 },
            a,
            [0.78, 0.78, 0.76],
            seed,
        ))
    }

    fn wood_material(&mut self) -> u16 {
        let seed = self.seed();
        let a = tint(self.rng, [0.55, 0.36, 0.2], 0.15);
        let b = tint(self.rng, [0.3, 0.18, 0.1], 0.08);
        let ring = self.rng.gen_range(0.01..0.04);
        self.material(Material::new(Pattern::Wood { ring }, a, b, seed))
    }

    fn fabric_material(&mut self) -> u16 {
        let seed = self.seed();
        let a = rgb(self.rng, 0.1, 0.9);
        let b = tint(self.rng, a, 0.3);
        let pattern = if self.rng.gen_bool(0.5) {
            Pattern::Noise { scale: 0.04 }
        } else {
            Pattern::Checker {
                size: self.rng.gen_range(0.04..0.12),
            }
        };
        self.material(Material::new(pattern, a, b, seed))
    }

    fn solid(&mut self, c: Rgb) -> u16 {
        let seed = self.seed();
        let c2 = tint(self.rng, c, 0.1);
        self.material(Material::new(Pattern::Plain, c, c2, seed))
    }

    fn painting_material(&mut self) -> u16 {
        let seed = self.seed();
        let a = rgb(self.rng, 0.1, 0.95);
        let b = rgb(self.rng, 0.1, 0.95);
        self.material(Material::new(Pattern::Painting, a, b, seed))
    }
}

/// Maps an item's local frame (x along the wall, z away from it, y up) to the world.
#[derive(Clone, Copy)]
struct Anchor {
    ox: f32,
    oz: f32,
    /// World direction of local +x: (dx, dz), one of the four axis directions.
    ax: (f32, f32),
    /// World direction of local +z.
    az: (f32, f32),
}

impl Anchor {
    fn world(&self, x: f32, z: f32) -> (f32, f32) {
        (
            self.ox + self.ax.0 * x + self.az.0 * z,
            self.oz + self.ax.1 * x + self.az.1 * z,
        )
    }
    fn aabb(&self, lmin: [f32; 3], lmax: [f32; 3]) -> (Vector3<f32>, Vector3<f32>) {
        let (x0, z0) = self.world(lmin[0], lmin[2]);
        let (x1, z1) = self.world(lmax[0], lmax[2]);
        (
            Vector3::new(x0.min(x1), lmin[1], z0.min(z1)),
            Vector3::new(x0.max(x1), lmax[1], z0.max(z1)),
        )
    }
    fn footprint(&self, w: f32, d: f32) -> Rect {
        let (a, b) = self.aabb([0.0, 0.0, 0.0], [w, 1.0, d]);
        Rect {
            x0: a.x,
            z0: a.z,
            x1: b.x,
            z1: b.z,
        }
    }
}

/// Split `rect` recursively into rooms, recording the door of every split line.
fn split_rooms(rng: &mut ChaCha8Rng, rect: Rect, doors: &mut Vec<Door>, rooms: &mut Vec<Rect>) {
    const MIN_SIDE: f32 = 2.4;
    let limit = rng.gen_range(4.2..6.5);
    let split_x = rect.w() >= rect.d();
    let (lo, hi) = if split_x {
        (rect.x0, rect.x1)
    } else {
        (rect.z0, rect.z1)
    };
    if hi - lo <= limit || hi - lo <= 2.0 * MIN_SIDE {
        rooms.push(rect);
        return;
    }
    // A split line must not run into an existing door on the rect's boundary.
    let blocked = |p: f32, doors: &[Door]| {
        doors.iter().any(|d| {
            let on_boundary = if split_x {
                d.along_x && ((d.at - rect.z0).abs() < 1e-3 || (d.at - rect.z1).abs() < 1e-3)
            } else {
                !d.along_x && ((d.at - rect.x0).abs() < 1e-3 || (d.at - rect.x1).abs() < 1e-3)
            };
            on_boundary && p > d.a - 0.6 && p < d.b + 0.6
        })
    };
    let (olo, ohi) = if split_x {
        (rect.z0, rect.z1)
    } else {
        (rect.x0, rect.x1)
    };
    // Too narrow across the split for a door with 0.4 m of wall on each side: keep it whole.
    if ohi - olo <= 0.8 + DOOR_WIDTH_M {
        rooms.push(rect);
        return;
    }
    let mut pos = None;
    for _ in 0..20 {
        let p = rng.gen_range(lo + MIN_SIDE..hi - MIN_SIDE);
        let p = (p * 20.0).round() / 20.0;
        if !blocked(p, doors) {
            pos = Some(p);
            break;
        }
    }
    let Some(p) = pos else {
        rooms.push(rect);
        return;
    };
    let a = rng.gen_range(olo + 0.4..ohi - 0.4 - DOOR_WIDTH_M);
    doors.push(Door {
        along_x: !split_x,
        at: p,
        a,
        b: a + DOOR_WIDTH_M,
    });
    let (r1, r2) = if split_x {
        (Rect { x1: p, ..rect }, Rect { x0: p, ..rect })
    } else {
        (Rect { z1: p, ..rect }, Rect { z0: p, ..rect })
    };
    split_rooms(rng, r1, doors, rooms);
    split_rooms(rng, r2, doors, rooms);
}

/// Subtract door intervals from [s0, s1]: the solid pieces of a wall line.
fn solid_pieces(s0: f32, s1: f32, holes: &[(f32, f32)]) -> Vec<(f32, f32)> {
    let mut holes: Vec<_> = holes.to_vec();
    holes.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut out = Vec::new();
    let mut cur = s0;
    for (a, b) in holes {
        if a > cur {
            out.push((cur, a.min(s1)));
        }
        cur = cur.max(b);
    }
    if cur < s1 {
        out.push((cur, s1));
    }
    out.into_iter().filter(|(a, b)| b - a > 1e-3).collect()
}

/// Generate one apartment whose floor area is about `area_m2`.
pub fn generate(name: &str, rng: &mut ChaCha8Rng, area_m2: f32, opts: &SceneOptions) -> Scene {
    let aspect = rng.gen_range(0.75..1.33f32);
    let width = (area_m2 * aspect).sqrt().max(3.0);
    let depth = (area_m2 / width).max(3.0);
    let ceiling = rng.gen_range(2.5..3.0f32);
    let mut doors = Vec::new();
    let mut rooms = Vec::new();
    split_rooms(
        rng,
        Rect {
            x0: 0.0,
            z0: 0.0,
            x1: width,
            z1: depth,
        },
        &mut doors,
        &mut rooms,
    );
    let lights = [
        Vector3::new(rng.gen_range(-0.6..0.6), 1.0, rng.gen_range(-0.6..0.6)).normalize(),
        Vector3::new(rng.gen_range(-1.0..1.0), 0.3, rng.gen_range(-1.0..1.0)).normalize(),
    ];
    let mut b = Builder {
        rng,
        boxes: Vec::new(),
        materials: Vec::new(),
        cats: vec![0],
        images: &opts.images,
    };
    // Palettes smaller than the room count: some rooms share a wallpaper or a floor, as in real homes.
    let n_wall = (rooms.len() * 3 / 4).max(2);
    let wall_palette: Vec<u16> = (0..n_wall).map(|_| b.wall_material()).collect();
    let n_floor = (rooms.len() / 2).max(2);
    let floor_palette: Vec<u16> = (0..n_floor).map(|_| b.floor_material()).collect();
    let ceiling_mat = b.ceiling_material();
    let door_mat = b.wood_material();

    for room in &rooms {
        let wall = *wall_palette.choose(b.rng).expect("non-empty");
        let floor = *floor_palette.choose(b.rng).expect("non-empty");
        let floor_id = b.instance("floor");
        b.add(
            Vector3::new(room.x0, -0.05, room.z0),
            Vector3::new(room.x1, 0.0, room.z1),
            floor,
            floor_id,
        );
        let ceil_id = b.instance("ceiling");
        b.add(
            Vector3::new(room.x0, ceiling, room.z0),
            Vector3::new(room.x1, ceiling + 0.05, room.z1),
            ceiling_mat,
            ceil_id,
        );
        let wall_id = b.instance("wall");
        // Four half-walls inside the room's rectangle; neighbours' halves meet back to back.
        for side in 0..4 {
            let (along_x, at, s0, s1) = match side {
                0 => (true, room.z0, room.x0, room.x1),
                1 => (true, room.z1, room.x0, room.x1),
                2 => (false, room.x0, room.z0, room.z1),
                _ => (false, room.x1, room.z0, room.z1),
            };
            let inward = if side % 2 == 0 { 1.0 } else { -1.0 };
            let holes: Vec<(f32, f32)> = doors
                .iter()
                .filter(|d| d.along_x == along_x && (d.at - at).abs() < 1e-3)
                .map(|d| (d.a, d.b))
                .collect();
            let mk = |p0: f32, p1: f32, y0: f32, y1: f32| {
                let (c0, c1) = (at, at + inward * WALL_HALF_M);
                let (n0, n1) = (c0.min(c1), c0.max(c1));
                if along_x {
                    (Vector3::new(p0, y0, n0), Vector3::new(p1, y1, n1))
                } else {
                    (Vector3::new(n0, y0, p0), Vector3::new(n1, y1, p1))
                }
            };
            for (p0, p1) in solid_pieces(s0, s1, &holes) {
                let (mn, mx) = mk(p0, p1, 0.0, ceiling);
                b.add(mn, mx, wall, wall_id);
            }
            for &(a, bb) in &holes {
                let (a, bb) = (a.max(s0), bb.min(s1));
                if bb > a {
                    let (mn, mx) = mk(a, bb, DOOR_HEIGHT_M, ceiling);
                    b.add(mn, mx, wall, wall_id);
                }
            }
        }
    }
    // Door frames: jambs and header around every opening, through the whole wall.
    for d in &doors {
        let id = b.instance("door");
        let (t0, t1) = (d.at - WALL_HALF_M - 0.02, d.at + WALL_HALF_M + 0.02);
        let parts = [
            (d.a, d.a + 0.06, 0.0, DOOR_HEIGHT_M + 0.06),
            (d.b - 0.06, d.b, 0.0, DOOR_HEIGHT_M + 0.06),
            (d.a, d.b, DOOR_HEIGHT_M, DOOR_HEIGHT_M + 0.06),
        ];
        for (p0, p1, y0, y1) in parts {
            let (mn, mx) = if d.along_x {
                (Vector3::new(p0, y0, t0), Vector3::new(p1, y1, t1))
            } else {
                (Vector3::new(t0, y0, p0), Vector3::new(t1, y1, p1))
            };
            b.add(mn, mx, door_mat, id);
        }
    }
    for room in rooms.clone() {
        furnish(&mut b, &room, &doors, width, depth, ceiling);
    }
    Scene {
        name: name.to_string(),
        boxes: b.boxes,
        materials: b.materials,
        instance_categories: b.cats,
        rooms,
        ceiling_m: ceiling,
        width_m: width,
        depth_m: depth,
        lights,
    }
}

/// Where [`twin`] joined the apartment to its copy: a door through the shared wall at x = `at_x`
/// (the original's width), spanning z in `z0..z1`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TwinDoor {
    /// The seam between the original and its copy, metres along x (the original's width).
    pub at_x: f32,
    /// Start of the opening along z, metres.
    pub z0: f32,
    /// End of the opening along z, metres.
    pub z1: f32,
}

/// The apartment and an exact copy of it beside it (translated by its width along +x), joined by one
/// door through the wall they share: every room has a look-alike `scene.width_m` metres away,
/// the same walls, furniture and textures, as rooms of a hotel corridor or an office floor repeat.
/// A map of one half and a drive into the other is the case of a stream that leaves its map into
/// a look-alike (issue 73) made on demand.
///
/// How: the door goes where an east room of the original and a west room of the copy share the
/// longest stretch of the seam; furniture within 1 m of the door on either side is removed, and
/// removed at the same place in the other half too, so the two halves differ only by the door's
/// opening. Instance ids of the copy follow the original's. `None` when no two rooms share 0.9 m of
/// the seam (the caller grows the apartment).
pub fn twin(scene: &Scene) -> Option<(Scene, TwinDoor)> {
    let w = scene.width_m;
    const EPS: f32 = 1e-3;
    let east = scene.rooms.iter().filter(|r| (r.x1 - w).abs() < EPS);
    let (z0, z1) = east
        .flat_map(|e| {
            scene
                .rooms
                .iter()
                .filter(|r| r.x0.abs() < EPS)
                .map(move |west| (e.z0.max(west.z0), e.z1.min(west.z1)))
        })
        .max_by(|a, b| (a.1 - a.0).total_cmp(&(b.1 - b.0)))?;
    // The opening, clear of both rooms' corners by 0.15 m.
    let width = DOOR_WIDTH_M.min(z1 - z0 - 0.3);
    if width < 0.9 - EPS {
        return None;
    }
    let mid = 0.5 * (z0 + z1);
    let door = TwinDoor {
        at_x: w,
        z0: mid - 0.5 * width,
        z1: mid + 0.5 * width,
    };
    let structural = ["wall", "floor", "ceiling", "door"].map(|c| category_id(c).expect("known"));
    let is_structural =
        |b: &SceneBox| structural.contains(&scene.instance_categories[b.instance as usize]);
    // Furniture near the door, in original coordinates: the original's side (x < w) and, moved
    // back by w, the copy's side (x > w).
    let clear = |b: &SceneBox| {
        let (za, zb) = (door.z0 - 0.3, door.z1 + 0.3);
        let near_z = b.min.z < zb && b.max.z > za;
        let near_original = b.max.x > w - 1.0;
        let near_copy = b.min.x < 1.0;
        near_z && (near_original || near_copy)
    };
    let kept: Vec<&SceneBox> = scene
        .boxes
        .iter()
        .filter(|b| is_structural(b) || !clear(b))
        .collect();
    let instances = scene.instance_categories.len() as u32 - 1;
    let shift = Vector3::new(w, 0.0, 0.0);
    let mut boxes: Vec<SceneBox> = kept.iter().map(|b| (*b).clone()).collect();
    boxes.extend(kept.iter().map(|b| SceneBox {
        min: b.min + shift,
        max: b.max + shift,
        faces: b.faces,
        instance: b.instance + instances,
    }));
    let mut instance_categories = scene.instance_categories.clone();
    instance_categories.extend_from_slice(&scene.instance_categories[1..]);
    // Cut the opening through both half-walls at the seam; a header stays above it.
    let wall = category_id("wall").expect("known");
    let mut cut = Vec::with_capacity(boxes.len() + 8);
    for b in boxes {
        let at_seam = b.min.x > w - WALL_HALF_M - EPS && b.max.x < w + WALL_HALF_M + EPS;
        let in_opening = b.min.z < door.z1 && b.max.z > door.z0 && b.min.y < EPS;
        let is_wall = instance_categories[b.instance as usize] == wall;
        if !(at_seam && in_opening && is_wall) {
            cut.push(b);
            continue;
        }
        for (z0, z1) in solid_pieces(b.min.z, b.max.z, &[(door.z0, door.z1)]) {
            let mut piece = b.clone();
            piece.min.z = z0;
            piece.max.z = z1;
            cut.push(piece);
        }
        let mut header = b.clone();
        header.min.z = door.z0.max(b.min.z);
        header.max.z = door.z1.min(b.max.z);
        header.min.y = DOOR_HEIGHT_M;
        if header.max.y > header.min.y && header.max.z > header.min.z {
            cut.push(header);
        }
    }
    let mut rooms = scene.rooms.clone();
    rooms.extend(scene.rooms.iter().map(|r| Rect {
        x0: r.x0 + w,
        x1: r.x1 + w,
        ..*r
    }));
    Some((
        Scene {
            name: scene.name.clone(),
            boxes: cut,
            materials: scene.materials.clone(),
            instance_categories,
            rooms,
            ceiling_m: scene.ceiling_m,
            width_m: 2.0 * w,
            depth_m: scene.depth_m,
            lights: scene.lights,
        },
        door,
    ))
}

/// The four walls of a room as anchors on the inner wall face, looking into the room.
fn wall_anchors(room: &Rect) -> [(Anchor, f32); 4] {
    let h = WALL_HALF_M;
    [
        // Wall at z0, items extend toward +z, local x along +x.
        (
            Anchor {
                ox: room.x0 + h,
                oz: room.z0 + h,
                ax: (1.0, 0.0),
                az: (0.0, 1.0),
            },
            room.w() - 2.0 * h,
        ),
        // Wall at z1, toward -z, local x along -x.
        (
            Anchor {
                ox: room.x1 - h,
                oz: room.z1 - h,
                ax: (-1.0, 0.0),
                az: (0.0, -1.0),
            },
            room.w() - 2.0 * h,
        ),
        // Wall at x0, toward +x, local x along -z.
        (
            Anchor {
                ox: room.x0 + h,
                oz: room.z1 - h,
                ax: (0.0, -1.0),
                az: (1.0, 0.0),
            },
            room.d() - 2.0 * h,
        ),
        // Wall at x1, toward -x, local x along +z.
        (
            Anchor {
                ox: room.x1 - h,
                oz: room.z0 + h,
                ax: (0.0, 1.0),
                az: (-1.0, 0.0),
            },
            room.d() - 2.0 * h,
        ),
    ]
}

#[derive(Clone, Copy, Debug)]
enum Item {
    Bed,
    Sofa,
    Cabinet,
    Drawers,
    Shelving,
    TvStand,
    Plant,
    Counter,
    Desk,
}

impl Item {
    fn size(self, rng: &mut ChaCha8Rng) -> (f32, f32) {
        match self {
            Item::Bed => (rng.gen_range(1.2..1.8), 2.0),
            Item::Sofa => (rng.gen_range(1.6..2.4), 0.9),
            Item::Cabinet => (rng.gen_range(0.6..1.2), 0.45),
            Item::Drawers => (rng.gen_range(0.7..1.1), 0.5),
            Item::Shelving => (rng.gen_range(0.7..1.4), 0.35),
            Item::TvStand => (rng.gen_range(1.0..1.6), 0.45),
            Item::Plant => (0.45, 0.45),
            Item::Counter => (rng.gen_range(1.6..2.8), 0.6),
            Item::Desk => (rng.gen_range(1.0..1.5), 0.65),
        }
    }
}

fn furnish(b: &mut Builder, room: &Rect, doors: &[Door], width: f32, depth: f32, ceiling: f32) {
    // Keep a 1 m deep clear zone on both sides of every door of this room.
    let mut taken: Vec<Rect> = doors
        .iter()
        .map(|d| {
            if d.along_x {
                Rect {
                    x0: d.a - 0.2,
                    x1: d.b + 0.2,
                    z0: d.at - 1.0,
                    z1: d.at + 1.0,
                }
            } else {
                Rect {
                    x0: d.at - 1.0,
                    x1: d.at + 1.0,
                    z0: d.a - 0.2,
                    z1: d.b + 0.2,
                }
            }
        })
        .collect();
    let inner = room.inset(WALL_HALF_M - 1e-3);
    let area = room.w() * room.d();
    let kind = b.rng.gen_range(0..4);
    let mut items: Vec<Item> = match kind {
        0 => vec![Item::Bed, Item::Drawers, Item::Plant, Item::Cabinet],
        1 => vec![Item::Sofa, Item::TvStand, Item::Shelving, Item::Plant],
        2 => vec![Item::Counter, Item::Cabinet, Item::Shelving],
        _ => vec![Item::Desk, Item::Shelving, Item::Drawers, Item::Plant],
    };
    if area < 9.0 {
        items.truncate(2);
    }
    let anchors = wall_anchors(room);
    let exterior = |a: &Anchor| {
        let (x, z) = a.world(0.0, -WALL_HALF_M);
        x <= 1e-3 || z <= 1e-3 || x >= width - 1e-3 || z >= depth - 1e-3
    };
    // Windows first, on exterior walls (they constrain nothing on the floor).
    let mut wall_spans: Vec<Vec<(f32, f32)>> = vec![Vec::new(); 4];
    for (k, (anchor, len)) in anchors.iter().enumerate() {
        if exterior(anchor) && *len > 1.8 && b.rng.gen_bool(0.7) {
            let w = b.rng.gen_range(0.8..(len - 0.6).min(1.8));
            let x = b.rng.gen_range(0.3..len - 0.3 - w);
            let y0 = b.rng.gen_range(0.8..1.0);
            let y1 = (y0 + b.rng.gen_range(1.0..1.4f32)).min(ceiling - 0.2);
            let seed = b.seed();
            let frame = rgb(b.rng, 0.7, 0.95);
            let mat = b.material(Material::new(Pattern::Window, frame, frame, seed));
            let id = b.instance("window");
            let (mn, mx) = anchor.aabb([x, y0, -0.01], [x + w, y1, 0.03]);
            b.add(mn, mx, mat, id);
            wall_spans[k].push((x, x + w));
        }
    }
    for item in items {
        let (w, d) = item.size(b.rng);
        for _ in 0..25 {
            let k = b.rng.gen_range(0..4);
            let (anchor, len) = anchors[k];
            if len < w + 0.1 {
                continue;
            }
            let x = b.rng.gen_range(0.05..len - w - 0.05);
            let local = Anchor {
                ox: anchor.world(x, 0.0).0,
                oz: anchor.world(x, 0.0).1,
                ..anchor
            };
            let fp = local.footprint(w, d);
            let grown = fp.inset(-0.05);
            if !inner.contains(&fp) || taken.iter().any(|t| t.overlaps(&grown)) {
                continue;
            }
            build_item(b, item, &local, w, d);
            taken.push(fp);
            wall_spans[k].push((x, x + w));
            break;
        }
    }
    // A table with chairs, or a rug, in the middle of larger rooms.
    if area > 10.0 {
        let (w, d) = (b.rng.gen_range(0.9..1.6), b.rng.gen_range(0.7..1.0));
        for _ in 0..15 {
            let cx = b.rng.gen_range(room.x0 + 1.0..room.x1 - 1.0);
            let cz = b.rng.gen_range(room.z0 + 1.0..room.z1 - 1.0);
            let anchor = Anchor {
                ox: cx - w / 2.0,
                oz: cz - d / 2.0,
                ax: (1.0, 0.0),
                az: (0.0, 1.0),
            };
            let fp = anchor.footprint(w, d).inset(-0.5);
            if !inner.contains(&fp) || taken.iter().any(|t| t.overlaps(&fp)) {
                continue;
            }
            if b.rng.gen_bool(0.6) {
                build_table_with_chairs(b, &anchor, w, d);
                taken.push(fp);
            } else {
                let seed = b.seed();
                let (ca, cb) = (rgb(b.rng, 0.2, 0.9), rgb(b.rng, 0.1, 0.7));
                let pat = if b.rng.gen_bool(0.5) {
                    Pattern::Painting
                } else {
                    Pattern::Dots {
                        spacing: 0.15,
                        radius: 0.04,
                    }
                };
                let mat = b.material(Material::new(pat, ca, cb, seed));
                let id = b.instance("objects");
                let (mn, mx) = anchor.aabb([-0.4, 0.0, -0.4], [w + 0.4, 0.012, d + 0.4]);
                b.add(mn, mx, mat, id);
            }
            break;
        }
    }
    // Pictures on walls, clear of doors, windows and tall furniture along the wall.
    let n_pictures = b.rng.gen_range(1..=4);
    for _ in 0..n_pictures {
        for _ in 0..10 {
            let k = b.rng.gen_range(0..4);
            let (anchor, len) = anchors[k];
            let w = b.rng.gen_range(0.35..1.2f32).min(len - 0.4);
            if w < 0.3 {
                continue;
            }
            let h = b.rng.gen_range(0.3..0.9f32);
            let x = b.rng.gen_range(0.2..len - 0.2 - w);
            let yc = b.rng.gen_range(1.35..1.75f32);
            let clash = wall_spans[k]
                .iter()
                .any(|&(a, c)| x < c + 0.1 && a < x + w + 0.1);
            let (wx0, wz0) = anchor.world(x, -0.1);
            let (wx1, wz1) = anchor.world(x + w, -0.1);
            let span = Rect {
                x0: wx0.min(wx1),
                z0: wz0.min(wz1),
                x1: wx0.max(wx1),
                z1: wz0.max(wz1),
            }
            .inset(-0.15);
            let at_door = doors.iter().any(|d| {
                let dr = if d.along_x {
                    Rect {
                        x0: d.a,
                        x1: d.b,
                        z0: d.at - 0.2,
                        z1: d.at + 0.2,
                    }
                } else {
                    Rect {
                        x0: d.at - 0.2,
                        x1: d.at + 0.2,
                        z0: d.a,
                        z1: d.b,
                    }
                };
                dr.overlaps(&span)
            });
            if clash || at_door {
                continue;
            }
            let mat = b.painting_material();
            let id = b.instance("picture");
            let (mn, mx) = anchor.aabb([x, yc - h / 2.0, 0.0], [x + w, yc + h / 2.0, 0.025]);
            b.add(mn, mx, mat, id);
            wall_spans[k].push((x, x + w));
            break;
        }
    }
}

fn build_item(b: &mut Builder, item: Item, a: &Anchor, w: f32, d: f32) {
    let put = |b: &mut Builder, lmin: [f32; 3], lmax: [f32; 3], mat: u16, id: u32| {
        let (mn, mx) = a.aabb(lmin, lmax);
        b.add(mn, mx, mat, id);
    };
    match item {
        Item::Bed => {
            let id = b.instance("bed");
            let wood = b.wood_material();
            let sheet = b.fabric_material();
            let pillow = b.solid([0.92, 0.92, 0.9]);
            put(b, [0.0, 0.0, 0.0], [w, 0.35, d], wood, id);
            put(b, [0.02, 0.35, 0.05], [w - 0.02, 0.55, d - 0.02], sheet, id);
            put(b, [0.0, 0.0, 0.0], [w, 1.0, 0.06], wood, id);
            let pw = (w - 0.3) / 2.0;
            put(b, [0.1, 0.55, 0.1], [0.1 + pw, 0.68, 0.45], pillow, id);
            put(
                b,
                [w - 0.1 - pw, 0.55, 0.1],
                [w - 0.1, 0.68, 0.45],
                pillow,
                id,
            );
        }
        Item::Sofa => {
            let id = b.instance("sofa");
            let fab = b.fabric_material();
            let cush = b.fabric_material();
            put(b, [0.0, 0.0, 0.0], [w, 0.42, d], fab, id);
            put(b, [0.0, 0.42, 0.0], [w, 0.85, 0.2], fab, id);
            put(b, [0.0, 0.42, 0.2], [0.18, 0.62, d], fab, id);
            put(b, [w - 0.18, 0.42, 0.2], [w, 0.62, d], fab, id);
            let n = ((w - 0.36) / 0.6).floor().max(1.0) as usize;
            let cw = (w - 0.36) / n as f32;
            for i in 0..n {
                let x0 = 0.18 + i as f32 * cw + 0.02;
                put(
                    b,
                    [x0, 0.42, 0.22],
                    [x0 + cw - 0.04, 0.52, d - 0.05],
                    cush,
                    id,
                );
            }
        }
        Item::Cabinet | Item::Drawers => {
            let (cat, h) = match item {
                Item::Cabinet => ("cabinet", b.rng.gen_range(0.8..2.0)),
                _ => ("chest_of_drawers", b.rng.gen_range(0.7..1.1)),
            };
            let id = b.instance(cat);
            let body = b.wood_material();
            let front_c = rgb(b.rng, 0.2, 0.9);
            let front = b.solid(front_c);
            let knob = b.solid([0.15, 0.15, 0.15]);
            put(b, [0.0, 0.0, 0.0], [w, h, d], body, id);
            let rows = if item == Item::Drawers { 3 } else { 2 };
            let rh = (h - 0.1) / rows as f32;
            for r in 0..rows {
                let y0 = 0.06 + r as f32 * rh;
                put(
                    b,
                    [0.04, y0, d],
                    [w - 0.04, y0 + rh - 0.04, d + 0.015],
                    front,
                    id,
                );
                let cx = w / 2.0;
                let cy = y0 + rh / 2.0;
                put(
                    b,
                    [cx - 0.06, cy - 0.015, d + 0.015],
                    [cx + 0.06, cy + 0.015, d + 0.04],
                    knob,
                    id,
                );
            }
        }
        Item::Shelving => {
            let id = b.instance("shelving");
            let wood = b.wood_material();
            let h = b.rng.gen_range(1.4..2.1);
            put(b, [0.0, 0.0, 0.0], [0.03, h, d], wood, id);
            put(b, [w - 0.03, 0.0, 0.0], [w, h, d], wood, id);
            put(b, [0.0, 0.0, 0.0], [w, h, 0.02], wood, id);
            let shelves = 4;
            let sh = h / shelves as f32;
            for s in 0..=shelves {
                let y = (s as f32 * sh).min(h - 0.03);
                put(b, [0.03, y, 0.0], [w - 0.03, y + 0.03, d], wood, id);
                if s == shelves {
                    break;
                }
                // Books: boxes of random colour and size.
                let mut x = 0.05;
                while x < w - 0.1 {
                    let bw = b.rng.gen_range(0.02..0.07);
                    let bh = b.rng.gen_range(0.5..0.85) * (sh - 0.05);
                    if b.rng.gen_bool(0.85) {
                        let book_c = rgb(b.rng, 0.05, 0.95);
                        let book = b.solid(book_c);
                        let bid = b.instance("objects");
                        let bd = b.rng.gen_range(0.6..0.95) * d;
                        put(
                            b,
                            [x, y + 0.03, 0.03],
                            [x + bw, y + 0.03 + bh, bd],
                            book,
                            bid,
                        );
                    }
                    x += bw + b.rng.gen_range(0.0..0.02);
                }
            }
        }
        Item::TvStand => {
            let id = b.instance("furniture");
            let body = b.wood_material();
            put(b, [0.0, 0.0, 0.0], [w, 0.5, d], body, id);
            let tv = b.instance("tv_monitor");
            let dark = b.solid([0.05, 0.05, 0.06]);
            let screen = b.painting_material();
            let tw = w * 0.8;
            let x0 = (w - tw) / 2.0;
            put(
                b,
                [x0, 0.5, 0.1],
                [x0 + tw, 0.5 + tw * 0.56, 0.16],
                dark,
                tv,
            );
            put(
                b,
                [x0 + 0.03, 0.53, 0.16],
                [x0 + tw - 0.03, 0.5 + tw * 0.56 - 0.03, 0.17],
                screen,
                tv,
            );
        }
        Item::Plant => {
            let id = b.instance("plant");
            let pot_c = rgb(b.rng, 0.3, 0.8);
            let pot = b.solid(pot_c);
            let seed = b.seed();
            let leaf = b.material(Material::new(
                Pattern::Noise { scale: 0.03 },
                [0.12, 0.45, 0.15],
                [0.05, 0.2, 0.05],
                seed,
            ));
            put(b, [0.08, 0.0, 0.08], [w - 0.08, 0.35, d - 0.08], pot, id);
            let h = b.rng.gen_range(0.9..1.6);
            put(b, [0.0, 0.35, 0.0], [w, h, d], leaf, id);
        }
        Item::Counter => {
            let id = b.instance("counter");
            let body_c = rgb(b.rng, 0.5, 0.95);
            let body = b.solid(body_c);
            let top = b.floor_material();
            put(b, [0.0, 0.0, 0.0], [w, 0.86, d - 0.02], body, id);
            put(b, [0.0, 0.86, 0.0], [w, 0.9, d], top, id);
            let up = b.instance("cabinet");
            let ub = b.wood_material();
            put(b, [0.0, 1.5, 0.0], [w, 2.2, 0.35], ub, up);
            let sink = b.instance("sink");
            let steel = b.solid([0.7, 0.72, 0.75]);
            put(
                b,
                [w * 0.3, 0.9, 0.1],
                [w * 0.3 + 0.5, 0.92, 0.5],
                steel,
                sink,
            );
        }
        Item::Desk => {
            let id = b.instance("table");
            let wood = b.wood_material();
            put(b, [0.0, 0.72, 0.0], [w, 0.76, d], wood, id);
            for (x, z) in [
                (0.0, 0.0),
                (w - 0.05, 0.0),
                (0.0, d - 0.05),
                (w - 0.05, d - 0.05),
            ] {
                put(b, [x, 0.0, z], [x + 0.05, 0.72, z + 0.05], wood, id);
            }
            let tv = b.instance("tv_monitor");
            let dark = b.solid([0.08, 0.08, 0.1]);
            let screen = b.painting_material();
            put(b, [w * 0.3, 0.76, 0.08], [w * 0.7, 1.15, 0.12], dark, tv);
            put(
                b,
                [w * 0.3 + 0.02, 0.78, 0.12],
                [w * 0.7 - 0.02, 1.13, 0.125],
                screen,
                tv,
            );
        }
    }
}

fn build_table_with_chairs(b: &mut Builder, a: &Anchor, w: f32, d: f32) {
    let id = b.instance("table");
    let wood = b.wood_material();
    let put = |b: &mut Builder, lmin: [f32; 3], lmax: [f32; 3], mat: u16, id: u32| {
        let (mn, mx) = a.aabb(lmin, lmax);
        b.add(mn, mx, mat, id);
    };
    put(b, [0.0, 0.72, 0.0], [w, 0.76, d], wood, id);
    for (x, z) in [
        (0.05, 0.05),
        (w - 0.1, 0.05),
        (0.05, d - 0.1),
        (w - 0.1, d - 0.1),
    ] {
        put(b, [x, 0.0, z], [x + 0.05, 0.72, z + 0.05], wood, id);
    }
    let seat = b.fabric_material();
    let frame = b.wood_material();
    for side in [-1.0f32, 1.0] {
        let cid = b.instance("chair");
        let x0 = w / 2.0 - 0.22;
        let (z0, z1, bz0, bz1) = if side < 0.0 {
            (-0.45, -0.05, -0.47, -0.43)
        } else {
            (d + 0.05, d + 0.45, d + 0.43, d + 0.47)
        };
        put(b, [x0, 0.0, z0], [x0 + 0.44, 0.45, z1], frame, cid);
        put(b, [x0, 0.45, z0], [x0 + 0.44, 0.5, z1], seat, cid);
        put(b, [x0, 0.5, bz0], [x0 + 0.44, 0.95, bz1], frame, cid);
    }
}

impl PartialEq for Item {
    fn eq(&self, other: &Self) -> bool {
        std::mem::discriminant(self) == std::mem::discriminant(other)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn generation_is_deterministic_and_has_rooms_doors_and_furniture() {
        let a = generate(
            "s",
            &mut ChaCha8Rng::seed_from_u64(5),
            120.0,
            &Default::default(),
        );
        let b = generate(
            "s",
            &mut ChaCha8Rng::seed_from_u64(5),
            120.0,
            &Default::default(),
        );
        assert_eq!(a.boxes.len(), b.boxes.len());
        assert_eq!(a.boxes[10].min, b.boxes[10].min);
        assert!(a.rooms.len() >= 3, "{} rooms", a.rooms.len());
        let cats: std::collections::HashSet<u8> = a.instance_categories.iter().copied().collect();
        for c in ["wall", "floor", "ceiling", "door", "picture"] {
            assert!(cats.contains(&category_id(c).unwrap()), "no {c}");
        }
        assert!(a
            .boxes
            .iter()
            .all(|b| b.min.x <= b.max.x && b.min.y <= b.max.y && b.min.z <= b.max.z));
    }

    #[test]
    fn large_apartments_of_many_seeds_generate_without_panicking() {
        // Seed 3 at this size once split a room too narrow to hold a door (an empty random range).
        for seed in 0..60 {
            for area in [12.0, 60.0, 150.0, 400.0] {
                let s = generate(
                    "s",
                    &mut ChaCha8Rng::seed_from_u64(seed),
                    area,
                    &Default::default(),
                );
                assert!(!s.rooms.is_empty());
            }
        }
    }

    #[test]
    fn a_twin_is_the_same_rooms_one_width_along_joined_by_an_open_door() {
        let mut joined = 0;
        for seed in 0..12 {
            let one = generate(
                "s",
                &mut ChaCha8Rng::seed_from_u64(seed),
                60.0,
                &Default::default(),
            );
            let Some((two, door)) = twin(&one) else {
                continue;
            };
            joined += 1;
            let w = one.width_m;
            assert_eq!(door.at_x, w);
            assert!((two.width_m - 2.0 * w).abs() < 1e-4 && two.depth_m == one.depth_m);
            assert_eq!(two.rooms.len(), 2 * one.rooms.len());
            // The robot passes the door and the metre either side of it.
            let obstacles = two.obstacles();
            let mid = 0.5 * (door.z0 + door.z1);
            for x in [w - 0.6, w, w + 0.6] {
                let clear = Scene::clearance(&obstacles, two.width_m, two.depth_m, x, mid);
                assert!(clear >= 0.3, "seed {seed}: clearance {clear} at x {x}");
            }
            // Away from the seam, every box of one half is a box of the other, moved by w.
            let key = |b: &SceneBox, dx: f32| {
                let r = |v: f32| (v * 1000.0).round() as i64;
                (
                    [r(b.min.x - dx), r(b.min.y), r(b.min.z)],
                    [r(b.max.x - dx), r(b.max.y), r(b.max.z)],
                    b.faces,
                )
            };
            let inside = |b: &&SceneBox, dx: f32| b.min.x - dx > 0.1 && b.max.x - dx < w - 0.1;
            let mut left: Vec<_> = (two.boxes.iter())
                .filter(|b| inside(b, 0.0))
                .map(|b| key(b, 0.0))
                .collect();
            let mut right: Vec<_> = (two.boxes.iter())
                .filter(|b| inside(b, w))
                .map(|b| key(b, w))
                .collect();
            left.sort();
            right.sort();
            assert!(!left.is_empty());
            assert_eq!(left, right, "seed {seed}: the halves differ");
        }
        assert!(joined >= 9, "only {joined} of 12 apartments joined");
    }

    #[test]
    fn door_pieces() {
        assert_eq!(
            solid_pieces(0.0, 5.0, &[(1.0, 2.0)]),
            vec![(0.0, 1.0), (2.0, 5.0)]
        );
        assert_eq!(solid_pieces(0.0, 5.0, &[]), vec![(0.0, 5.0)]);
    }
}
