//! Procedural surface textures: deterministic functions of surface coordinates.
//!
//! Every pattern is a pure function of (world-plane coordinates, face-local coordinates, seed), so a
//! surface looks the same from every camera: what a keypoint detector finds in one view it can find in
//! another. Patterns carry corners and blobs at several scales (bricks, tiles, dots, paintings), and all
//! of them get a low-amplitude fractal noise so that no surface is perfectly flat in colour.

use std::sync::Arc;

/// An RGB colour with components in 0..1.
pub type Rgb = [f32; 3];

/// An image used as a tiling texture (from `--textures DIR`).
#[derive(Debug)]
pub struct TextureImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// RGB in 0..1, row-major.
    pub data: Vec<Rgb>,
}

/// The kind of pattern and its parameters (lengths in metres).
#[derive(Debug, Clone)]
pub enum Pattern {
    /// Colour `a` with a gentle noise toward `b`.
    Plain,
    /// Fractal value noise between `a` and `b` (marble, plaster, fabric, foliage).
    Noise {
        /// Feature size.
        scale: f32,
    },
    /// Checkerboard of `a` and `b`.
    Checker {
        /// Square size.
        size: f32,
    },
    /// Stripes of `a` and `b`.
    Stripes {
        /// Period.
        period: f32,
        /// Share of the period in colour `a`.
        duty: f32,
        /// True for vertical stripes (along the plane's second axis).
        vertical: bool,
    },
    /// Running-bond bricks in colour `a` with per-brick variation, mortar `b`.
    Bricks {
        /// Brick length.
        w: f32,
        /// Brick height.
        h: f32,
    },
    /// Square tiles `a` with grout lines `b`, per-tile variation.
    Tiles {
        /// Tile size.
        size: f32,
    },
    /// Wood grain rings of `a` and `b`.
    Wood {
        /// Ring spacing.
        ring: f32,
    },
    /// Dots of `b` on `a`.
    Dots {
        /// Grid spacing.
        spacing: f32,
        /// Dot radius.
        radius: f32,
    },
    /// A framed abstract painting over the face (uses face-local coordinates).
    Painting,
    /// A window: frame `a`, mullions, and a sky-and-city view.
    Window,
    /// A user image, tiled with the given size in metres.
    Image {
        /// The image.
        image: Arc<TextureImage>,
        /// Size of one tile.
        tile: f32,
    },
}

/// A surface material.
#[derive(Debug, Clone)]
pub struct Material {
    /// The pattern.
    pub pattern: Pattern,
    /// Primary colour.
    pub a: Rgb,
    /// Secondary colour.
    pub b: Rgb,
    /// Seed of the pattern's randomness.
    pub seed: u32,
}

#[inline]
fn hash3(x: i32, y: i32, seed: u32) -> u32 {
    let mut h = (x as u32).wrapping_mul(0x8da6_b343)
        ^ (y as u32).wrapping_mul(0xd816_3841)
        ^ seed.wrapping_mul(0xcb1a_b31f);
    h ^= h >> 15;
    h = h.wrapping_mul(0x2c1b_3c6d);
    h ^= h >> 12;
    h = h.wrapping_mul(0x297a_2d39);
    h ^= h >> 15;
    h
}

/// Uniform value in 0..1 from integer lattice coordinates and a seed.
#[inline]
pub fn hash01(x: i32, y: i32, seed: u32) -> f32 {
    (hash3(x, y, seed) >> 8) as f32 / (1u32 << 24) as f32
}

/// `floor` without a libm call (the baseline x86-64 target has no rounding instruction); exact for
/// |x| < 2^31, which texture coordinates in metres always are.
#[inline(always)]
pub fn ffloor(x: f32) -> f32 {
    let i = x as i32 as f32;
    if x < i {
        i - 1.0
    } else {
        i
    }
}

#[inline]
fn smooth(t: f32) -> f32 {
    t * t * (3.0 - 2.0 * t)
}

/// Smooth value noise in 0..1.
pub fn value_noise(x: f32, y: f32, seed: u32) -> f32 {
    let (xf, yf) = (ffloor(x), ffloor(y));
    let (xi, yi) = (xf as i32, yf as i32);
    let (tx, ty) = (smooth(x - xf), smooth(y - yf));
    let a = hash01(xi, yi, seed);
    let b = hash01(xi + 1, yi, seed);
    let c = hash01(xi, yi + 1, seed);
    let d = hash01(xi + 1, yi + 1, seed);
    let top = a + (b - a) * tx;
    let bot = c + (d - c) * tx;
    top + (bot - top) * ty
}

/// Four octaves of value noise, in 0..1.
pub fn fbm(x: f32, y: f32, seed: u32) -> f32 {
    let mut sum = 0.0;
    let mut amp = 0.5;
    let mut f = 1.0;
    for o in 0..4u32 {
        sum += amp * value_noise(x * f, y * f, seed.wrapping_add(o * 7919));
        amp *= 0.5;
        f *= 2.03;
    }
    sum / 0.9375
}

#[inline]
fn mix(a: Rgb, b: Rgb, t: f32) -> Rgb {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

#[inline]
fn scale(c: Rgb, s: f32) -> Rgb {
    [c[0] * s, c[1] * s, c[2] * s]
}

impl Material {
    /// A material with the given pattern and colours.
    pub fn new(pattern: Pattern, a: Rgb, b: Rgb, seed: u32) -> Self {
        Self {
            pattern,
            a,
            b,
            seed,
        }
    }

    /// The albedo at a surface point. `(u, v)` are world coordinates in the face's plane (metres),
    /// `(lu, lv)` the position within the face in 0..1.
    pub fn albedo(&self, u: f32, v: f32, lu: f32, lv: f32) -> Rgb {
        let s = self.seed;
        let base = match &self.pattern {
            Pattern::Plain => mix(self.a, self.b, 0.15 * fbm(u * 3.0, v * 3.0, s)),
            Pattern::Noise { scale: sc } => {
                let n = fbm(u / sc, v / sc, s);
                mix(self.a, self.b, smooth(n.clamp(0.0, 1.0)))
            }
            Pattern::Checker { size } => {
                let c = (ffloor(u / size) as i64 + ffloor(v / size) as i64) & 1;
                if c == 0 {
                    self.a
                } else {
                    self.b
                }
            }
            Pattern::Stripes {
                period,
                duty,
                vertical,
            } => {
                let x = if *vertical { u } else { v };
                let f = (x / period).rem_euclid(1.0);
                if f < *duty {
                    self.a
                } else {
                    self.b
                }
            }
            Pattern::Bricks { w, h } => {
                let row = ffloor(v / h);
                let off = if (row as i64) & 1 == 0 { 0.0 } else { 0.5 * w };
                let col = ffloor((u + off) / w);
                let fu = (u + off) / w - col;
                let fv = v / h - row;
                let mortar = 0.04 * (w / h).max(1.0);
                if fu < mortar / (w / h) || fv < mortar {
                    self.b
                } else {
                    let j = hash01(col as i32, row as i32, s);
                    scale(self.a, 0.8 + 0.35 * j)
                }
            }
            Pattern::Tiles { size } => {
                let (cu, cv) = (ffloor(u / size), ffloor(v / size));
                let (fu, fv) = (u / size - cu, v / size - cv);
                if fu < 0.05 || fv < 0.05 {
                    self.b
                } else {
                    let j = hash01(cu as i32, cv as i32, s);
                    scale(self.a, 0.85 + 0.25 * j)
                }
            }
            Pattern::Wood { ring } => {
                let warp = fbm(u * 0.8, v * 4.0, s) * 2.0;
                let r = ((v * 0.3 + u * 0.05 + warp * ring) / ring).sin() * 0.5 + 0.5;
                mix(self.a, self.b, r * r)
            }
            Pattern::Dots { spacing, radius } => {
                let (cu, cv) = ((u / spacing).round(), (v / spacing).round());
                let (du, dv) = (u - cu * spacing, v - cv * spacing);
                let jit = 0.6 + 0.6 * hash01(cu as i32, cv as i32, s);
                if du * du + dv * dv < radius * radius * jit * jit {
                    self.b
                } else {
                    self.a
                }
            }
            Pattern::Painting => painting(lu, lv, s, self.a, self.b),
            Pattern::Window => window(lu, lv, s, self.a),
            Pattern::Image { image, tile } => {
                let x = ((u / tile).rem_euclid(1.0) * image.width as f32) as u32;
                let y = ((1.0 - (v / tile).rem_euclid(1.0)) * image.height as f32) as u32;
                let x = x.min(image.width - 1);
                let y = y.min(image.height - 1);
                image.data[(y * image.width + x) as usize]
            }
        };
        // Fine grain everywhere: surfaces are never perfectly uniform.
        let grain = 0.92 + 0.16 * value_noise(u * 40.0, v * 40.0, s ^ 0x55aa);
        scale(base, grain)
    }
}

/// A deterministic abstract painting: a background gradient with rectangles, discs and bands.
fn painting(x: f32, y: f32, seed: u32, a: Rgb, b: Rgb) -> Rgb {
    // Frame.
    if !(0.06..=0.94).contains(&x) || !(0.06..=0.94).contains(&y) {
        return [0.12, 0.09, 0.06];
    }
    let mut c = mix(a, b, y);
    let n = 5 + (hash3(0, 0, seed) % 7) as i32;
    for k in 0..n {
        let r = |j: i32| hash01(k, j, seed);
        let col = [r(10), r(11), r(12)];
        let (cx, cy) = (r(1), r(2));
        let size = 0.08 + 0.3 * r(3);
        let inside = match hash3(k, 4, seed) % 3 {
            0 => (x - cx).abs() < size * (0.5 + r(5)) && (y - cy).abs() < size,
            1 => (x - cx).powi(2) + (y - cy).powi(2) < size * size,
            _ => ((x + y * r(6)) * 7.0 + r(7) * 6.0).sin() > 0.6 && (y - cy).abs() < size,
        };
        if inside {
            c = col;
        }
    }
    c
}

/// A window: frame, mullions, a sky gradient above a skyline.
fn window(x: f32, y: f32, seed: u32, frame: Rgb) -> Rgb {
    let f = 0.05;
    if x < f || x > 1.0 - f || y < f || y > 1.0 - f || (x - 0.5).abs() < f * 0.5 {
        return frame;
    }
    if (y - 0.55).abs() < f * 0.4 {
        return frame;
    }
    let bx = ffloor(x * 9.0) as i32;
    let height = 0.15 + 0.35 * hash01(bx, 0, seed);
    if y < height {
        let lit = hash01((x * 60.0) as i32, (y * 40.0) as i32, seed) > 0.7;
        return if lit {
            [0.9, 0.85, 0.6]
        } else {
            [0.35, 0.36, 0.4]
        };
    }
    mix([0.75, 0.85, 0.95], [0.45, 0.62, 0.9], y)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_is_deterministic_and_bounded() {
        for i in 0..1000 {
            let (x, y) = (i as f32 * 0.37, i as f32 * 0.11);
            let n = fbm(x, y, 7);
            assert!((0.0..=1.0).contains(&n));
            assert_eq!(n, fbm(x, y, 7));
        }
        assert_ne!(fbm(0.3, 0.4, 1), fbm(0.3, 0.4, 2));
    }

    #[test]
    fn patterns_vary_over_a_surface() {
        let m = Material::new(
            Pattern::Bricks { w: 0.25, h: 0.08 },
            [0.7, 0.3, 0.2],
            [0.8; 3],
            3,
        );
        let samples: Vec<Rgb> = (0..50)
            .map(|i| m.albedo(i as f32 * 0.031, i as f32 * 0.017, 0.5, 0.5))
            .collect();
        let spread = samples
            .iter()
            .map(|c| c[0])
            .fold(f32::INFINITY, f32::min)
            .max(0.0);
        let top = samples.iter().map(|c| c[0]).fold(0.0, f32::max);
        assert!(top - spread > 0.1);
    }
}
