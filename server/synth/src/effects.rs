//! Robot camera effects for queries: what a real RGB-D camera on a moving robot adds to a clean render.
//!
//! Colour: exposure gain, gamma, white balance, a Gaussian blur of about one to two pixels (focus and
//! motion), sensor noise, and JPEG compression. Depth (a structured-light / stereo sensor model): noise
//! whose standard deviation grows with the square of the range, random dropouts, and lost depth at
//! depth discontinuities. Every draw comes from `seed`, so the same seed perturbs a frame the same way.
//! Database views stay clean, as a careful mapping run would be.

use nalgebra::Vector3;
use pntr_core::{DepthMap, RgbImage};
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};

use crate::render::Lighting;
use crate::scene::Scene;

/// The effect groups `--realism` and `--effects` name, in order.
pub const EFFECT_GROUPS: [&str; 6] = ["lighting", "exposure", "blur", "noise", "jpeg", "depth"];

/// How strong each effect is; [`RobotEffects::default`] is a typical indoor robot camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobotEffects {
    /// Exposure gain drawn from this range.
    pub gain: (f64, f64),
    /// Gamma drawn from this range.
    pub gamma: (f64, f64),
    /// Per-channel white-balance factor drawn from 1 +- this.
    pub white_balance: f64,
    /// Blur sigma in pixels drawn from this range.
    pub blur_sigma_px: (f64, f64),
    /// Sensor noise standard deviation, grey levels.
    pub noise_levels: f64,
    /// JPEG quality drawn from this range (1..100).
    pub jpeg_quality: (u8, u8),
    /// Depth noise: sigma = this * z^2 (metres).
    pub depth_noise_per_m2: f64,
    /// Share of depth pixels dropped at random.
    pub depth_dropout: f64,
    /// Depth jump (metres) to a 4-neighbour above which a pixel's depth is lost.
    pub depth_edge_m: f64,
}

impl Default for RobotEffects {
    fn default() -> Self {
        Self {
            gain: (0.6, 1.5),
            gamma: (0.8, 1.25),
            white_balance: 0.08,
            blur_sigma_px: (0.5, 1.5),
            noise_levels: 4.0,
            jpeg_quality: (30, 70),
            depth_noise_per_m2: 0.003,
            depth_dropout: 0.05,
            depth_edge_m: 0.15,
        }
    }
}

impl RobotEffects {
    /// The default effects with only the named groups on (`exposure`: gain, gamma and white
    /// balance; `blur`; `noise`; `jpeg`; `depth`: range noise, dropouts and lost edges), the others
    /// neutral. `lighting` is not a frame effect (see [`Realism`]) and is ignored here.
    ///
    /// # Errors
    /// A name that is not one of [`EFFECT_GROUPS`].
    pub fn only(groups: &[&str]) -> Result<Self, String> {
        let all = Self::default();
        let mut fx = Self {
            gain: (1.0, 1.0),
            gamma: (1.0, 1.0),
            white_balance: 0.0,
            blur_sigma_px: (0.0, 0.0),
            noise_levels: 0.0,
            jpeg_quality: (100, 100),
            depth_noise_per_m2: 0.0,
            depth_dropout: 0.0,
            depth_edge_m: f64::INFINITY,
        };
        for g in groups {
            match *g {
                "lighting" => {}
                "exposure" => {
                    fx.gain = all.gain;
                    fx.gamma = all.gamma;
                    fx.white_balance = all.white_balance;
                }
                "blur" => fx.blur_sigma_px = all.blur_sigma_px,
                "noise" => fx.noise_levels = all.noise_levels,
                "jpeg" => fx.jpeg_quality = all.jpeg_quality,
                "depth" => {
                    fx.depth_noise_per_m2 = all.depth_noise_per_m2;
                    fx.depth_dropout = all.depth_dropout;
                    fx.depth_edge_m = all.depth_edge_m;
                }
                other => {
                    return Err(format!(
                        "unknown effect {other:?} (one of {}, or robot for all)",
                        EFFECT_GROUPS.join(", ")
                    ))
                }
            }
        }
        Ok(fx)
    }

    /// The exposure of one capture (gain, gamma, white balance), drawn for `seed` (the same draw as
    /// [`RobotEffects::apply`] makes).
    pub fn look(&self, seed: u64) -> Look {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_0fc0_ffee);
        Self::draw_look(self, &mut rng)
    }

    fn draw_look(&self, rng: &mut rand_chacha::ChaCha8Rng) -> Look {
        let gain = rng.gen_range(self.gain.0..=self.gain.1);
        let gamma = rng.gen_range(self.gamma.0..=self.gamma.1);
        let white_balance =
            std::array::from_fn(|_| 1.0 + rng.gen_range(-self.white_balance..=self.white_balance));
        Look {
            gain,
            gamma,
            white_balance,
        }
    }

    /// The exposure of frame `i` of a recording: it drifts smoothly from one draw to the next over
    /// [`DRIFT_FRAMES`] frames, as a camera's auto exposure follows the light, instead of jumping
    /// at every frame. `base` seeds the recording.
    pub fn drifting_look(&self, base: u64, i: usize) -> Look {
        let (a, b, t) = drift(base, i);
        self.look(a).lerp(&self.look(b), t)
    }

    /// Apply every effect to one frame, deterministically for `seed`. A blur sigma of 0 blurs
    /// nothing, JPEG quality 100 skips compression.
    pub fn apply(&self, rgb: &mut RgbImage, depth: &mut DepthMap, seed: u64) {
        let look = self.look(seed);
        self.apply_with(rgb, depth, &look, seed);
    }

    /// As [`RobotEffects::apply`] with the exposure `look` given (a recording's drifting one); blur,
    /// noise, JPEG and depth are drawn for `seed`.
    pub fn apply_with(&self, rgb: &mut RgbImage, depth: &mut DepthMap, look: &Look, seed: u64) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_0fc0_ffee);
        // The look's draws come first in the stream; skip them so a frame's other effects are the
        // same whichever look it gets.
        let _ = self.draw_look(&mut rng);
        let Look {
            gain,
            gamma,
            white_balance: wb,
        } = *look;
        let sigma = rng.gen_range(self.blur_sigma_px.0..=self.blur_sigma_px.1);
        let quality = rng.gen_range(self.jpeg_quality.0..=self.jpeg_quality.1);
        let (w, h) = (rgb.width as usize, rgb.height as usize);
        let mut planes: Vec<Vec<f64>> = (0..3)
            .map(|c| (0..w * h).map(|i| rgb.data[i * 3 + c] as f64).collect())
            .collect();
        if sigma > 0.0 {
            for p in &mut planes {
                blur(p, w, h, sigma);
            }
        }
        let noise = Normal::new(0.0, self.noise_levels).expect("finite sigma");
        for i in 0..w * h {
            for (c, plane) in planes.iter().enumerate() {
                let v = (plane[i] / 255.0 * gain * wb[c])
                    .clamp(0.0, 1.0)
                    .powf(gamma)
                    * 255.0
                    + noise.sample(&mut rng);
                rgb.data[i * 3 + c] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
        if quality < 100 {
            jpeg_round_trip(rgb, quality);
        }
        // Depth.
        let orig = depth.data.clone();
        for r in 0..h {
            for c in 0..w {
                let i = r * w + c;
                let z = orig[i] as f64;
                if z <= 0.0 {
                    continue;
                }
                let mut lost = rng.gen_bool(self.depth_dropout);
                for (dc, dr) in [(1i64, 0i64), (-1, 0), (0, 1), (0, -1)] {
                    let (nc, nr) = (c as i64 + dc, r as i64 + dr);
                    if nc >= 0 && nr >= 0 && (nc as usize) < w && (nr as usize) < h {
                        let n = orig[nr as usize * w + nc as usize] as f64;
                        lost |= n > 0.0 && (n - z).abs() > self.depth_edge_m;
                    }
                }
                depth.data[i] = if lost {
                    0.0
                } else {
                    let s = self.depth_noise_per_m2 * z * z;
                    (z + s * rng.sample::<f64, _>(rand_distr::StandardNormal)).max(0.0) as f32
                };
            }
        }
    }
}

/// Frames over which a recording's lighting and exposure drift from one draw to the next (3 s at
/// 10 Hz).
pub const DRIFT_FRAMES: usize = 30;

/// The two draws frame `i` of a recording seeded `base` blends, and the weight of the second.
fn drift(base: u64, i: usize) -> (u64, u64, f64) {
    let k = (i / DRIFT_FRAMES) as u64;
    let seed = |k: u64| base ^ k.wrapping_add(1).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    let t = (i % DRIFT_FRAMES) as f64 / DRIFT_FRAMES as f64;
    (seed(k), seed(k + 1), t)
}

/// A capture's exposure: gain, gamma and per-channel white balance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Look {
    /// Exposure gain.
    pub gain: f64,
    /// Gamma.
    pub gamma: f64,
    /// Per-channel (R, G, B) factors.
    pub white_balance: [f64; 3],
}

impl Look {
    /// `self` moved toward `other` by `t` (0..1).
    pub fn lerp(&self, other: &Look, t: f64) -> Look {
        let l = |a: f64, b: f64| a + (b - a) * t;
        Look {
            gain: l(self.gain, other.gain),
            gamma: l(self.gamma, other.gamma),
            white_balance: std::array::from_fn(|c| {
                l(self.white_balance[c], other.white_balance[c])
            }),
        }
    }
}

/// What `synth --realism` puts on a robot's captures (queries and drives; database views stay as
/// the mapping run saw them): other lighting ([`Realism::lighting_of`]: each room's lamps at another
/// level, drawn once per scene; ambient and directional lights drawn per query, drifting smoothly
/// along a drive) and the camera's frame effects ([`RobotEffects`]). Deterministic for the same seeds.
#[derive(Debug, Clone, PartialEq)]
pub struct Realism {
    /// Light queries otherwise than the map.
    pub lighting: bool,
    /// Frame effects (neutral groups do nothing).
    pub effects: RobotEffects,
}

impl Realism {
    /// `robot` (everything), `none` (`None`), or a comma-separated list of [`EFFECT_GROUPS`].
    ///
    /// # Errors
    /// An unknown name.
    pub fn parse(spec: &str) -> Result<Option<Self>, String> {
        match spec.trim() {
            "none" => Ok(None),
            "robot" => Ok(Some(Self {
                lighting: true,
                effects: RobotEffects::default(),
            })),
            list => {
                let groups: Vec<&str> = list.split(',').map(str::trim).collect();
                Ok(Some(Self {
                    lighting: groups.contains(&"lighting"),
                    effects: RobotEffects::only(&groups)?,
                }))
            }
        }
    }

    /// The lighting of frame `i` of a recording seeded `base` (a robot's drive): it drifts smoothly
    /// from one draw of [`Realism::lighting_of`] to the next over [`DRIFT_FRAMES`] frames.
    pub fn drifting_lighting(
        &self,
        scene: &Scene,
        scene_seed: u64,
        base: u64,
        i: usize,
    ) -> Lighting {
        let (a, b, t) = drift(base, i);
        self.lighting_of(scene, scene_seed, a)
            .lerp(&self.lighting_of(scene, scene_seed, b), t as f32)
    }

    /// The lighting of one capture of `scene`: the scene's own when `lighting` is off; otherwise each
    /// room's gain drawn from `scene_seed` (0.55-1.25: lamps off, dimmed or brighter than when
    /// mapped), and per capture from `capture_seed` the ambient level (x0.75-1.15), the lights'
    /// strengths (x0.5-1.5) and the second light's direction (a lamp or window elsewhere).
    pub fn lighting_of(&self, scene: &Scene, scene_seed: u64, capture_seed: u64) -> Lighting {
        let mut l = Lighting::of(scene);
        if !self.lighting {
            return l;
        }
        let mut rooms = rand_chacha::ChaCha8Rng::seed_from_u64(scene_seed ^ 0x1a9b_7c0f);
        l.room_gain = scene
            .rooms
            .iter()
            .map(|_| rooms.gen_range(0.55f32..=1.25))
            .collect();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(capture_seed ^ 0x11e7_0ca7);
        l.ambient *= rng.gen_range(0.75f32..=1.15);
        for light in &mut l.lights {
            light.0 *= rng.gen_range(0.5f32..=1.5);
        }
        let yaw = rng.gen_range(0.0f32..std::f32::consts::TAU);
        let up = rng.gen_range(0.2f32..=0.9);
        let flat = (1.0 - up * up).sqrt();
        l.lights[1].1 = Vector3::new(flat * yaw.cos(), up, flat * yaw.sin());
        l
    }
}

fn blur(p: &mut [f64], w: usize, h: usize, sigma: f64) {
    let radius = (3.0 * sigma).ceil() as i64;
    let kernel: Vec<f64> = (-radius..=radius)
        .map(|x| (-(x * x) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let sum: f64 = kernel.iter().sum();
    let kernel: Vec<f64> = kernel.iter().map(|k| k / sum).collect();
    // Rows, then columns: one separable pass each, edges clamped.
    let mut tmp = vec![0.0; p.len()];
    convolve(p, &mut tmp, w, h, &kernel, (1, w));
    convolve(&tmp, p, h, w, &kernel, (w, 1));
}

/// Convolve `lines` lines of `len` samples (`step.0` apart, lines `step.1` apart) with `kernel`.
fn convolve(
    src: &[f64],
    dst: &mut [f64],
    len: usize,
    lines: usize,
    kernel: &[f64],
    step: (usize, usize),
) {
    let radius = (kernel.len() / 2) as i64;
    for l in 0..lines {
        for i in 0..len {
            dst[l * step.1 + i * step.0] = kernel
                .iter()
                .enumerate()
                .map(|(k, wt)| {
                    let x = (i as i64 + k as i64 - radius).clamp(0, len as i64 - 1) as usize;
                    wt * src[l * step.1 + x * step.0]
                })
                .sum();
        }
    }
}

/// The small perturbations of a frame an answer must survive (issue 41, `pntr eval --stability`):
/// each leaves the scene and the camera as they are and changes only what any capture changes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Perturbation {
    /// The colour image through JPEG at quality 90 (one step of a camera's compression setting).
    Jpeg90,
    /// Colour and depth moved one pixel to the right (the edge column repeated), as a camera
    /// nudged by a fraction of a degree.
    ShiftOnePixel,
}

impl Perturbation {
    /// Every perturbation, in report order.
    pub const ALL: [Perturbation; 2] = [Perturbation::Jpeg90, Perturbation::ShiftOnePixel];

    /// The name reports use: `jpeg90`, `shift1px`.
    pub fn name(self) -> &'static str {
        match self {
            Perturbation::Jpeg90 => "jpeg90",
            Perturbation::ShiftOnePixel => "shift1px",
        }
    }

    /// Apply to a frame in place.
    pub fn apply(self, rgb: &mut RgbImage, depth: &mut DepthMap) {
        match self {
            Perturbation::Jpeg90 => jpeg_round_trip(rgb, 90),
            Perturbation::ShiftOnePixel => {
                shift_right(&mut rgb.data, rgb.width as usize, 3);
                shift_right(&mut depth.data, depth.width as usize, 1);
            }
        }
    }
}

/// Move every row of a `width`-pixel image (`channels` values a pixel) one pixel right, repeating
/// the first column.
fn shift_right<T: Copy>(data: &mut [T], width: usize, channels: usize) {
    if width < 2 {
        return;
    }
    for row in data.chunks_exact_mut(width * channels) {
        row.copy_within(0..(width - 1) * channels, channels);
    }
}

fn jpeg_round_trip(rgb: &mut RgbImage, quality: u8) {
    let mut bytes = Vec::new();
    let enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, quality.clamp(1, 100));
    let encoded = image::ImageEncoder::write_image(
        enc,
        &rgb.data,
        rgb.width,
        rgb.height,
        image::ExtendedColorType::Rgb8,
    );
    if encoded.is_err() {
        return;
    }
    if let Ok(img) = image::load_from_memory_with_format(&bytes, image::ImageFormat::Jpeg) {
        let img = img.to_rgb8();
        if img.width() == rgb.width && img.height() == rgb.height {
            rgb.data = img.into_raw();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn perturbations_change_only_what_they_say() {
        let (w, h) = (8u32, 4u32);
        let rgb0 = RgbImage {
            width: w,
            height: h,
            data: (0..w * h * 3).map(|i| (i * 7 % 251) as u8).collect(),
        };
        let depth0 = DepthMap {
            width: w,
            height: h,
            data: (0..w * h).map(|i| 1.0 + i as f32 * 0.01).collect(),
        };
        let (mut rgb, mut depth) = (rgb0.clone(), depth0.clone());
        Perturbation::ShiftOnePixel.apply(&mut rgb, &mut depth);
        for y in 0..h as usize {
            for x in 1..w as usize {
                let (to, from) = (y * w as usize + x, y * w as usize + x - 1);
                assert_eq!(depth.data[to], depth0.data[from]);
                assert_eq!(
                    rgb.data[to * 3..to * 3 + 3],
                    rgb0.data[from * 3..from * 3 + 3]
                );
            }
            assert_eq!(depth.data[y * w as usize], depth0.data[y * w as usize]);
        }
        let (mut rgb, mut depth) = (rgb0.clone(), depth0.clone());
        Perturbation::Jpeg90.apply(&mut rgb, &mut depth);
        assert_eq!(depth.data, depth0.data, "JPEG leaves depth alone");
        assert_eq!(rgb.data.len(), rgb0.data.len());
        assert_eq!(
            Perturbation::ALL.map(Perturbation::name),
            ["jpeg90", "shift1px"]
        );
    }

    /// A 32x32 frame of varied colour, all of it 2 m away.
    fn textured_wall() -> (RgbImage, DepthMap) {
        let rgb = RgbImage::new(
            32,
            32,
            (0..32 * 32 * 3).map(|i| (i * 7 % 251) as u8).collect(),
        )
        .unwrap();
        (
            rgb,
            DepthMap::from_metres(32, 32, vec![2.0; 32 * 32]).unwrap(),
        )
    }

    #[test]
    fn effects_are_deterministic_and_change_the_frame() {
        let (rgb, depth) = textured_wall();
        let run = |seed| {
            let (mut r, mut d) = (rgb.clone(), depth.clone());
            RobotEffects::default().apply(&mut r, &mut d, seed);
            (r, d)
        };
        let (a, da) = run(1);
        let (b, db) = run(1);
        let (c, _) = run(2);
        assert_eq!(a, b);
        assert_eq!(da, db);
        assert_ne!(a, c);
        assert_ne!(a, rgb);
        let dropped = da.data.iter().filter(|&&z| z == 0.0).count();
        assert!(dropped > 0 && dropped < 200, "{dropped}");
        assert!(da
            .data
            .iter()
            .filter(|&&z| z > 0.0)
            .all(|&z| (z - 2.0).abs() < 0.1));
    }

    #[test]
    fn effect_groups_switch_on_one_at_a_time() {
        let (rgb, depth) = textured_wall();
        let run = |fx: RobotEffects| {
            let (mut r, mut d) = (rgb.clone(), depth.clone());
            fx.apply(&mut r, &mut d, 3);
            (r, d)
        };
        let (r, d) = run(RobotEffects::only(&[]).unwrap());
        assert_eq!(
            (r, d),
            (rgb.clone(), depth.clone()),
            "no group changes nothing"
        );
        let (r, d) = run(RobotEffects::only(&["depth"]).unwrap());
        assert_eq!(r, rgb, "depth leaves colour alone");
        assert_ne!(d, depth);
        for g in ["exposure", "blur", "noise", "jpeg"] {
            let (r, d) = run(RobotEffects::only(&[g]).unwrap());
            assert_ne!(r, rgb, "{g}");
            assert_eq!(d, depth, "{g} leaves depth alone");
        }
        assert!(RobotEffects::only(&["fog"]).unwrap_err().contains("fog"));
        assert_eq!(Realism::parse("none").unwrap(), None);
        let robot = Realism::parse("robot").unwrap().unwrap();
        assert!(robot.lighting && robot.effects == RobotEffects::default());
        let some = Realism::parse("lighting,blur").unwrap().unwrap();
        assert!(some.lighting && some.effects.noise_levels == 0.0);
        assert!(Realism::parse("").is_err());
    }

    #[test]
    fn a_recording_s_exposure_drifts_instead_of_jumping() {
        let fx = RobotEffects::default();
        let looks: Vec<Look> = (0..4 * DRIFT_FRAMES)
            .map(|i| fx.drifting_look(9, i))
            .collect();
        let biggest_step = looks
            .windows(2)
            .map(|w| (w[1].gain - w[0].gain).abs())
            .fold(0.0, f64::max);
        let range = looks.iter().map(|l| l.gain).fold(f64::MIN, f64::max)
            - looks.iter().map(|l| l.gain).fold(f64::MAX, f64::min);
        assert!(
            range > 0.1,
            "the exposure changes over the recording: {range}"
        );
        assert!(
            biggest_step <= 0.9 / DRIFT_FRAMES as f64 + 1e-9,
            "one frame moves the gain by at most its range over {DRIFT_FRAMES} frames: {biggest_step}"
        );
        // A frame's own effects do not depend on the look it gets.
        let rgb = RgbImage::new(8, 8, vec![100; 8 * 8 * 3]).unwrap();
        let depth = DepthMap::from_metres(8, 8, vec![1.0; 64]).unwrap();
        let (mut a, mut da) = (rgb.clone(), depth.clone());
        fx.apply(&mut a, &mut da, 5);
        let (mut b, mut db) = (rgb, depth);
        fx.apply_with(&mut b, &mut db, &fx.look(5), 5);
        assert_eq!((a, da), (b, db));
    }
}
