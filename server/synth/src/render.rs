//! Ray casting of a box scene into RGB, planar depth and instance labels.
//!
//! A bounding-volume hierarchy (median split, leaves of up to four boxes) keeps a frame at a few
//! milliseconds for scenes of a few thousand boxes; [`Renderer::render_brute_force`] exists to measure
//! what the hierarchy buys in the benchmark and to cross-check it in tests.

use nalgebra::{Isometry3, Vector3};
use pntr_core::{convert_axes, CameraAxes, DepthMap, Intrinsics, LabelMap, RgbImage};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;

use crate::scene::Scene;

/// Depth beyond this is clipped, as in HPointLoc (normalised depth 1.0).
pub const MAX_DEPTH_M: f32 = 10.0;

#[derive(Debug, Clone, Copy)]
struct Node {
    min: Vector3<f32>,
    max: Vector3<f32>,
    /// Leaf: first box index into `order`; inner: index of the left child (right = left + 1).
    start: u32,
    /// Leaf: number of boxes; 0 for an inner node.
    count: u32,
}

/// A scene prepared for rendering.
pub struct Renderer<'s> {
    scene: &'s Scene,
    nodes: Vec<Node>,
    order: Vec<u32>,
}

/// How a view is lit: an ambient term, two directional lights, and a gain per room (a room's lamps).
/// [`Lighting::of`] is the scene's own lighting, what the database views (the mapping run) see;
/// `synth --realism` lights queries otherwise ([`crate::effects::Realism`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Lighting {
    /// Light reaching every surface whatever its orientation (shade units; the scene's: 0.5).
    pub ambient: f32,
    /// Strength (shade units) and unit direction toward each directional light.
    pub lights: [(f32, Vector3<f32>); 2],
    /// Gain on the shade of surfaces in each room (indexed like [`Scene::rooms`], by the floor
    /// position of the surface point); surfaces outside every room, and all when empty, get 1.
    pub room_gain: Vec<f32>,
}

impl Lighting {
    /// The scene's own lighting.
    pub fn of(scene: &Scene) -> Self {
        Self {
            ambient: 0.5,
            lights: [(0.35, scene.lights[0]), (0.2, scene.lights[1])],
            room_gain: Vec::new(),
        }
    }

    /// `self` moved toward `other` by `t` (0..1): levels and room gains blended, directions
    /// blended and renormalised.
    pub fn lerp(&self, other: &Lighting, t: f32) -> Lighting {
        let l = |a: f32, b: f32| a + (b - a) * t;
        let dir = |a: &Vector3<f32>, b: &Vector3<f32>| {
            let d = a + (b - a) * t;
            if d.norm() > 1e-6 {
                d.normalize()
            } else {
                *a
            }
        };
        Lighting {
            ambient: l(self.ambient, other.ambient),
            lights: std::array::from_fn(|k| {
                (
                    l(self.lights[k].0, other.lights[k].0),
                    dir(&self.lights[k].1, &other.lights[k].1),
                )
            }),
            room_gain: self
                .room_gain
                .iter()
                .zip(&other.room_gain)
                .map(|(a, b)| l(*a, *b))
                .collect(),
        }
    }

    /// Shade of a surface with normal `n` at world point `p`.
    fn shade(&self, scene: &Scene, n: &Vector3<f32>, p: &Vector3<f32>) -> f32 {
        let shade = self.ambient
            + self.lights[0].0 * n.dot(&self.lights[0].1).max(0.0)
            + self.lights[1].0 * n.dot(&self.lights[1].1).max(0.0);
        if self.room_gain.is_empty() {
            return shade;
        }
        let room = scene
            .rooms
            .iter()
            .position(|r| p.x >= r.x0 && p.x <= r.x1 && p.z >= r.z0 && p.z <= r.z1);
        shade
            * room
                .and_then(|i| self.room_gain.get(i))
                .copied()
                .unwrap_or(1.0)
    }
}

/// One rendered frame.
pub struct Frame {
    /// Colour with sensor noise.
    pub rgb: RgbImage,
    /// Planar depth, metres (clipped at [`MAX_DEPTH_M`]; 0 where the ray hit nothing).
    pub depth: DepthMap,
    /// Instance id per pixel.
    pub labels: LabelMap,
}

#[derive(Clone, Copy)]
struct Hit {
    t: f32,
    index: u32,
    axis: usize,
    positive: bool,
}

/// Slab test of a ray (origin `o`, inverse direction `inv`) against a box: the entry and exit ray
/// parameters, entry clamped at 0. Branch-free: the hot loop of the renderer.
#[inline(always)]
fn fmin(a: f32, b: f32) -> f32 {
    // Plain compare-select (one `minss`); `f32::min`'s NaN handling costs more and no NaN occurs
    // here: 0 * inf only arises for rays parallel to a slab, which the comparisons then reject.
    if a < b {
        a
    } else {
        b
    }
}

#[inline(always)]
fn fmax(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// Slab test of a ray (origin `o`, inverse direction `inv`) against a box: the entry and exit ray
/// parameters, entry clamped at 0. Branch-free: the hot loop of the renderer.
#[inline(always)]
fn slab(o: &[f32; 3], inv: &[f32; 3], mn: &Vector3<f32>, mx: &Vector3<f32>) -> (f32, f32) {
    let ax = (mn.x - o[0]) * inv[0];
    let bx = (mx.x - o[0]) * inv[0];
    let ay = (mn.y - o[1]) * inv[1];
    let by = (mx.y - o[1]) * inv[1];
    let az = (mn.z - o[2]) * inv[2];
    let bz = (mx.z - o[2]) * inv[2];
    let t0 = fmax(fmax(fmax(fmin(ax, bx), fmin(ay, by)), fmin(az, bz)), 0.0);
    let t1 = fmin(fmin(fmax(ax, bx), fmax(ay, by)), fmax(az, bz));
    (t0, t1)
}

/// The axis through whose face the ray enters the box (the one with the largest entry parameter).
fn entry_axis(o: &[f32; 3], inv: &[f32; 3], mn: &Vector3<f32>, mx: &Vector3<f32>) -> usize {
    let mut best = (f32::NEG_INFINITY, 0);
    for a in 0..3 {
        let ta = (mn[a] - o[a]) * inv[a];
        let tb = (mx[a] - o[a]) * inv[a];
        let near = ta.min(tb);
        if near > best.0 {
            best = (near, a);
        }
    }
    best.1
}

impl<'s> Renderer<'s> {
    /// Build the hierarchy over the scene's boxes.
    pub fn new(scene: &'s Scene) -> Self {
        let mut order: Vec<u32> = (0..scene.boxes.len() as u32).collect();
        let mut nodes = Vec::with_capacity(2 * scene.boxes.len());
        nodes.push(Node {
            min: Vector3::zeros(),
            max: Vector3::zeros(),
            start: 0,
            count: 0,
        });
        Self::build(scene, &mut nodes, &mut order, 0, 0, scene.boxes.len());
        Self {
            scene,
            nodes,
            order,
        }
    }

    fn build(
        scene: &Scene,
        nodes: &mut Vec<Node>,
        order: &mut [u32],
        node: usize,
        lo: usize,
        hi: usize,
    ) {
        let mut mn = Vector3::repeat(f32::INFINITY);
        let mut mx = Vector3::repeat(f32::NEG_INFINITY);
        for &i in &order[lo..hi] {
            let b = &scene.boxes[i as usize];
            mn = mn.inf(&b.min);
            mx = mx.sup(&b.max);
        }
        nodes[node].min = mn;
        nodes[node].max = mx;
        if hi - lo <= 4 {
            nodes[node].start = lo as u32;
            nodes[node].count = (hi - lo) as u32;
            return;
        }
        // Binned surface-area heuristic: large walls and floors next to small books make a median
        // split poor, SAH keeps big boxes high in the tree and small ones in tight leaves.
        let area = |a: &Vector3<f32>, b: &Vector3<f32>| {
            let e = (b - a).sup(&Vector3::zeros());
            e.x * e.y + e.y * e.z + e.z * e.x
        };
        let centre = |i: u32, axis: usize| {
            let b = &scene.boxes[i as usize];
            0.5 * (b.min[axis] + b.max[axis])
        };
        const BINS: usize = 12;
        let mut best: Option<(f32, usize, f32)> = None;
        for axis in 0..3 {
            let (mut cmin, mut cmax) = (f32::INFINITY, f32::NEG_INFINITY);
            for &i in &order[lo..hi] {
                let c = centre(i, axis);
                cmin = cmin.min(c);
                cmax = cmax.max(c);
            }
            if cmax - cmin < 1e-6 {
                continue;
            }
            let mut bmin = [Vector3::repeat(f32::INFINITY); BINS];
            let mut bmax = [Vector3::repeat(f32::NEG_INFINITY); BINS];
            let mut bcount = [0usize; BINS];
            let bin_of =
                |c: f32| (((c - cmin) / (cmax - cmin) * BINS as f32) as usize).min(BINS - 1);
            for &i in &order[lo..hi] {
                let k = bin_of(centre(i, axis));
                let b = &scene.boxes[i as usize];
                bmin[k] = bmin[k].inf(&b.min);
                bmax[k] = bmax[k].sup(&b.max);
                bcount[k] += 1;
            }
            for split in 1..BINS {
                let (mut lmin, mut lmax, mut lc) = (
                    Vector3::repeat(f32::INFINITY),
                    Vector3::repeat(f32::NEG_INFINITY),
                    0,
                );
                for k in 0..split {
                    lmin = lmin.inf(&bmin[k]);
                    lmax = lmax.sup(&bmax[k]);
                    lc += bcount[k];
                }
                let (mut rmin, mut rmax, mut rc) = (
                    Vector3::repeat(f32::INFINITY),
                    Vector3::repeat(f32::NEG_INFINITY),
                    0,
                );
                for k in split..BINS {
                    rmin = rmin.inf(&bmin[k]);
                    rmax = rmax.sup(&bmax[k]);
                    rc += bcount[k];
                }
                if lc == 0 || rc == 0 {
                    continue;
                }
                let cost = area(&lmin, &lmax) * lc as f32 + area(&rmin, &rmax) * rc as f32;
                if best.is_none_or(|(c, _, _)| cost < c) {
                    let pos = cmin + (cmax - cmin) * split as f32 / BINS as f32;
                    best = Some((cost, axis, pos));
                }
            }
        }
        let mid = match best {
            Some((_, axis, pos)) => {
                let slice = &mut order[lo..hi];
                let mut m = 0;
                for j in 0..slice.len() {
                    if centre(slice[j], axis) < pos {
                        slice.swap(j, m);
                        m += 1;
                    }
                }
                lo + m
            }
            None => (lo + hi) / 2,
        };
        let mid = if mid == lo || mid == hi {
            (lo + hi) / 2
        } else {
            mid
        };
        let left = nodes.len();
        for _ in 0..2 {
            nodes.push(Node {
                min: Vector3::zeros(),
                max: Vector3::zeros(),
                start: 0,
                count: 0,
            });
        }
        nodes[node].start = left as u32;
        nodes[node].count = 0;
        Self::build(scene, nodes, order, left, lo, mid);
        Self::build(scene, nodes, order, left + 1, mid, hi);
    }

    #[inline(always)]
    fn test_box(&self, i: u32, o: &[f32; 3], inv: &[f32; 3], best: &mut Option<Hit>) {
        let b = &self.scene.boxes[i as usize];
        let (t0, t1) = slab(o, inv, &b.min, &b.max);
        if t0 <= t1 && t0 > 1e-4 && best.is_none_or(|h| t0 < h.t) {
            let axis = entry_axis(o, inv, &b.min, &b.max);
            *best = Some(Hit {
                t: t0,
                index: i,
                axis,
                positive: inv[axis] < 0.0,
            });
        }
    }

    fn trace(&self, o: &[f32; 3], d: &Vector3<f32>, hint: Option<u32>) -> Option<Hit> {
        let inv = [1.0 / d.x, 1.0 / d.y, 1.0 / d.z];
        let mut best: Option<Hit> = None;
        // Neighbouring pixels mostly hit the same box: testing it first gives a tight bound that
        // prunes most of the hierarchy.
        if let Some(i) = hint {
            self.test_box(i, o, &inv, &mut best);
        }
        // Stack of (node, entry distance); a node is skipped when its entry is beyond the best hit.
        let mut stack = [(0u32, 0.0f32); 64];
        let mut sp = 0;
        let root = self.entry(0, o, &inv);
        if root.is_finite() {
            stack[0] = (0, root);
            sp = 1;
        }
        while sp > 0 {
            sp -= 1;
            let (id, t_in) = stack[sp];
            if best.is_some_and(|h| t_in >= h.t) {
                continue;
            }
            let n = &self.nodes[id as usize];
            if n.count > 0 {
                for k in n.start..n.start + n.count {
                    self.test_box(self.order[k as usize], o, &inv, &mut best);
                }
            } else if sp + 2 <= stack.len() {
                // Visit the nearer child first so the far one is usually pruned by the best hit.
                let (l, r) = (n.start, n.start + 1);
                let tl = self.entry(l, o, &inv);
                let tr = self.entry(r, o, &inv);
                let ((near, tn), (far, tf)) = if tl <= tr {
                    ((l, tl), (r, tr))
                } else {
                    ((r, tr), (l, tl))
                };
                if tf.is_finite() {
                    stack[sp] = (far, tf);
                    sp += 1;
                }
                if tn.is_finite() {
                    stack[sp] = (near, tn);
                    sp += 1;
                }
            }
        }
        best
    }

    #[inline(always)]
    fn entry(&self, node: u32, o: &[f32; 3], inv: &[f32; 3]) -> f32 {
        let n = &self.nodes[node as usize];
        let (t0, t1) = slab(o, inv, &n.min, &n.max);
        if t0 <= t1 {
            t0
        } else {
            f32::INFINITY
        }
    }

    fn trace_brute(&self, o: &[f32; 3], d: &Vector3<f32>) -> Option<Hit> {
        let inv = [1.0 / d.x, 1.0 / d.y, 1.0 / d.z];
        let mut best = None;
        for i in 0..self.scene.boxes.len() as u32 {
            self.test_box(i, o, &inv, &mut best);
        }
        best
    }

    /// Render the view of a camera at `world_from_camera` (Habitat axes, as HPointLoc stores poses)
    /// through `k`, lens distortion included.
    /// `noise_seed` drives the RGB sensor noise (Gaussian, sigma 0.02 of full scale, as HPointLoc).
    pub fn render(
        &self,
        world_from_camera: &Isometry3<f64>,
        k: &Intrinsics,
        noise_seed: u64,
    ) -> Frame {
        self.render_with(
            world_from_camera,
            k,
            noise_seed,
            &Lighting::of(self.scene),
            false,
        )
    }

    /// As [`Renderer::render`] under another `lighting`.
    pub fn render_lit(
        &self,
        world_from_camera: &Isometry3<f64>,
        k: &Intrinsics,
        noise_seed: u64,
        lighting: &Lighting,
    ) -> Frame {
        self.render_with(world_from_camera, k, noise_seed, lighting, false)
    }

    /// The scene rendered.
    pub fn scene(&self) -> &Scene {
        self.scene
    }

    /// As [`Renderer::render`] but testing every box for every ray (no hierarchy).
    pub fn render_brute_force(
        &self,
        world_from_camera: &Isometry3<f64>,
        k: &Intrinsics,
        noise_seed: u64,
    ) -> Frame {
        self.render_with(
            world_from_camera,
            k,
            noise_seed,
            &Lighting::of(self.scene),
            true,
        )
    }

    fn render_with(
        &self,
        world_from_camera: &Isometry3<f64>,
        k: &Intrinsics,
        noise_seed: u64,
        lighting: &Lighting,
        brute: bool,
    ) -> Frame {
        let cv = convert_axes(world_from_camera, CameraAxes::Habitat, CameraAxes::OpenCv);
        let r = cv.rotation.to_rotation_matrix().matrix().cast::<f32>();
        let o = cv.translation.vector.cast::<f32>();
        let (w, h) = (k.width as usize, k.height as usize);
        let mut rgb = vec![0u8; w * h * 3];
        let mut depth = vec![0f32; w * h];
        let mut labels = vec![0u32; w * h];
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(noise_seed);
        let noise = Normal::new(0.0f32, 0.02 * 255.0).expect("valid sigma");
        let scene = self.scene;
        let mut last = None;
        for row in 0..h {
            for col in 0..w {
                // The ray the (possibly distorted) lens sends through this pixel.
                let (x, y) =
                    k.undistort_normalized((col as f64 - k.cx) / k.fx, (row as f64 - k.cy) / k.fy);
                let dc = Vector3::new(x as f32, y as f32, 1.0);
                // Direction with camera-z component 1: the hit's ray parameter is its planar depth.
                let d = r * dc;
                let oa = [o.x, o.y, o.z];
                let hit = if brute {
                    self.trace_brute(&oa, &d)
                } else {
                    self.trace(&oa, &d, last)
                };
                last = hit.map(|h| h.index);
                let px = row * w + col;
                let mut colour = [0.0f32; 3];
                if let Some(hit) = hit {
                    let b = &scene.boxes[hit.index as usize];
                    let p = o + d * hit.t;
                    let mut n = Vector3::zeros();
                    n[hit.axis] = if hit.positive { 1.0 } else { -1.0 };
                    let (ua, va) = match hit.axis {
                        0 => (2, 1),
                        1 => (0, 2),
                        _ => (0, 1),
                    };
                    let lu = (p[ua] - b.min[ua]) / (b.max[ua] - b.min[ua]).max(1e-6);
                    let lv = (p[va] - b.min[va]) / (b.max[va] - b.min[va]).max(1e-6);
                    let face = hit.axis * 2 + hit.positive as usize;
                    let mat = &scene.materials[b.faces[face] as usize];
                    let albedo = mat.albedo(p[ua], p[va], lu, lv);
                    let shade = lighting.shade(scene, &n, &p);
                    colour = [albedo[0] * shade, albedo[1] * shade, albedo[2] * shade];
                    depth[px] = hit.t.min(MAX_DEPTH_M);
                    labels[px] = b.instance;
                }
                for c in 0..3 {
                    let v = colour[c] * 255.0 + noise.sample(&mut rng);
                    rgb[px * 3 + c] = (v.clamp(0.0, 255.0) + 0.5) as u8;
                }
            }
        }
        Frame {
            rgb: RgbImage::new(k.width, k.height, rgb).expect("sized"),
            depth: DepthMap {
                width: k.width,
                height: k.height,
                data: depth,
            },
            labels: LabelMap::new(k.width, k.height, labels).expect("sized"),
        }
    }
}
