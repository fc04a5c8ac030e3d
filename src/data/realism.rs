//! Crops a camera would recognise: the object under 1–3 coloured lights with a random material,
//! on a procedural background, with other objects behind it and in front of it, sometimes cut by
//! the frame's edge, cut out around a box that errs as a detector's does, and passed through a
//! camera model (exposure, white balance, gamma, blur, noise, JPEG).
//!
//! Every randomised factor is drawn from one of two disjoint sets ([`Split`]): training draws
//! from even bands of each range and from its own background families and photographs, the
//! held-out evaluation from the odd bands and other families and photographs
//! (`assets/backgrounds/`, public domain or CC0, sources in `SOURCES.md` there). A model that scores well on the held-out split has met
//! colours, lights, materials and backgrounds it was never trained on.
//!
//! Everything comes from the `rng` a crop is made with: one seed, one crop.

use std::sync::Arc;

use nalgebra::{Rotation3, Vector3};
use rand::{Rng, RngExt};

use crate::cad::{
    Camera, CornerNormals, Light, Lighting, Material, Mesh, Pose, Render, SceneObject, SceneRaster,
    Shape,
};
use crate::data::virtual_crop::{
    FRAME_DISTANCE, VirtualCamera, frame_camera, object_box, placement_at_depth,
};
use crate::so3::haar_rotation;

/// Crease angle of the shading normals: edges sharper than this stay hard.
pub const CREASE_DEG: f32 = 35.0;

/// The display gamma the crops are encoded with (sRGB's, approximated): colours drawn as sRGB
/// are decoded with it, and the camera encodes with it (times its own random factor).
const GAMMA: f32 = 2.2;

/// Which of the two disjoint sets of ranges a crop's randomisation draws from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Split {
    /// Training: even bands, noise / shapes / gradient backgrounds.
    Train,
    /// Held-out evaluation: odd bands, stripe / cell / blob backgrounds.
    HeldOut,
}

impl std::str::FromStr for Split {
    type Err = String;

    /// `train` or `held-out`, as the probes and reports name the splits.
    fn from_str(s: &str) -> Result<Split, String> {
        match s {
            "train" => Ok(Split::Train),
            "held-out" => Ok(Split::HeldOut),
            other => Err(format!("the split is train or held-out, not {other}")),
        }
    }
}

/// How realistic crops are made.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Realism {
    /// The ranges drawn from.
    pub split: Split,
    /// Largest standard deviation of a box edge's error, as a fraction of the box's side (each
    /// crop draws its own σ up to this; 0: the exact box).
    pub box_jitter: f64,
    /// Chance that other objects share the crop (behind, and sometimes in front).
    pub clutter: f64,
    /// Chance that the object is placed where the frame's edge may cut it.
    pub truncation: f64,
    /// Share of crops rendered plain instead (flat grey on black, the exact box): one more
    /// variation, so that clean renders stay in the training distribution.
    pub plain: f64,
    /// Factors held at one neutral value (for probes that ask which factor a model misses;
    /// training and evaluation vary every one).
    pub neutral: Neutral,
}

/// Randomised factors of a realistic crop that can be held at one neutral value. Each is still
/// drawn from the crop's generator and then replaced (the camera, the crop's last draw, is not
/// drawn), so a crop keeps its pose and every other factor's draw whichever are neutral.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Neutral {
    /// A matte mid-grey material (the mesh's own colours, where it has them, under white).
    pub material: bool,
    /// One white light from the camera's upper left and a dim white ambient.
    pub lighting: bool,
    /// A black background, as the flat renders have (distractors behind still drawn).
    pub background: bool,
    /// No camera effects: exposure 1, no white balance, saturation or gamma change beyond sRGB's
    /// 2.2, no blur, noise or JPEG.
    pub camera: bool,
}

impl Neutral {
    /// Every factor varies.
    pub const NONE: Neutral = Neutral {
        material: false,
        lighting: false,
        background: false,
        camera: false,
    };

    /// The material a neutral crop gets.
    fn material(has_colours: bool) -> Material {
        Material {
            base: if has_colours { [1.0; 3] } else { [0.35; 3] },
            roughness: 0.8,
            metalness: 0.0,
        }
    }

    /// The lighting a neutral crop gets.
    fn lighting() -> Lighting {
        Lighting {
            lights: vec![Light {
                direction: Vector3::new(-0.4, -0.5, -1.0).normalize(),
                radiance: [1.6; 3],
            }],
            ambient: [0.12; 3],
        }
    }

    /// The subject's material and the scene's lights: drawn for `split`, then replaced where
    /// neutral.
    fn draw_look<R: Rng + ?Sized>(
        self,
        rng: &mut R,
        split: Split,
        has_colours: bool,
    ) -> (Material, Lighting) {
        let material = random_material(rng, split, has_colours);
        let lighting = random_lighting(rng, split);
        (
            if self.material {
                Neutral::material(has_colours)
            } else {
                material
            },
            if self.lighting {
                Neutral::lighting()
            } else {
                lighting
            },
        )
    }

    /// The `n × n` background: drawn for `split`, then black where neutral.
    fn draw_background<R: Rng + ?Sized>(self, rng: &mut R, split: Split, n: usize) -> Vec<Rgb> {
        let mut back = background(rng, split, n);
        if self.background {
            back.fill([0.0; 3]);
        }
        back
    }

    /// The camera's RGB8 image of a linear one: [`camera_effects`], or sRGB's gamma alone where
    /// neutral (nothing drawn then: the camera is the crop's last draw).
    fn draw_camera<R: Rng + ?Sized>(
        self,
        rng: &mut R,
        split: Split,
        linear: &[[f32; 3]],
        size: usize,
    ) -> Vec<u8> {
        if self.camera {
            plain_camera(linear)
        } else {
            camera_effects(rng, split, linear, size)
        }
    }
}

impl Realism {
    /// Training crops: detector-like boxes (σ up to 12 % of the side per edge), clutter in 80 %
    /// of them, a quarter placed where the frame may cut them, one in ten plain.
    pub const TRAIN: Realism = Realism {
        split: Split::Train,
        box_jitter: 0.12,
        clutter: 0.8,
        truncation: 0.25,
        plain: 0.1,
        neutral: Neutral::NONE,
    };

    /// Held-out crops around the exact box, none plain.
    pub const HELD_OUT: Realism = Realism {
        split: Split::HeldOut,
        box_jitter: 0.0,
        clutter: 0.8,
        truncation: 0.25,
        plain: 0.0,
        neutral: Neutral::NONE,
    };

    /// Held-out crops with a detector's box error of σ = `sigma` × side per edge (every crop).
    pub fn held_out_boxes(sigma: f64) -> Realism {
        Realism {
            box_jitter: -sigma.abs(),
            ..Realism::HELD_OUT
        }
    }

    /// The σ of one crop's box error: `|box_jitter|` exactly when negative (a fixed error, for
    /// evaluation), else uniform in `[0, box_jitter]`.
    fn draw_box_sigma<R: Rng + ?Sized>(&self, rng: &mut R) -> f64 {
        if self.box_jitter < 0.0 {
            -self.box_jitter
        } else if self.box_jitter > 0.0 {
            rng.random_range(0.0..self.box_jitter)
        } else {
            0.0
        }
    }
}

/// What realistic crops are made of, built once: the objects' meshes and shading normals, and
/// the distractors that fill the scene around them (the objects themselves and primitives).
#[derive(Debug)]
pub struct SceneAssets {
    /// The realism.
    pub realism: Realism,
    meshes: Vec<Mesh>,
    normals: Vec<CornerNormals>,
    distractors: Vec<(Mesh, CornerNormals)>,
}

impl SceneAssets {
    /// Assets for `meshes` (NOCS, in object order).
    pub fn new(meshes: &[Mesh], realism: Realism) -> Arc<SceneAssets> {
        let normals = meshes
            .iter()
            .map(|m| CornerNormals::new(m, CREASE_DEG))
            .collect();
        let mut distractors: Vec<Mesh> = meshes.to_vec();
        distractors.extend(
            [
                Shape::Cube,
                Shape::Cylinder,
                Shape::Tetrahedron,
                Shape::Cone,
            ]
            .iter()
            .map(|s| s.mesh()),
        );
        distractors.push(crate::cad::shapes::uv_sphere_mesh(16, 8));
        let distractors = distractors
            .into_iter()
            .map(|m| {
                let n = CornerNormals::new(&m, CREASE_DEG);
                (m, n)
            })
            .collect();
        Arc::new(SceneAssets {
            realism,
            meshes: meshes.to_vec(),
            normals,
            distractors,
        })
    }
}

/// A realistic crop.
pub struct RealisticCrop {
    /// `size² × 3` RGB8.
    pub rgb: Vec<u8>,
    /// The subject as the virtual camera saw it at `size · supersample` (mask, depth and NOCS of
    /// its visible pixels only: hidden and out-of-frame parts excluded).
    pub render: Render,
    /// The object's rotation in the crop's virtual camera (the label).
    pub r_virtual: Rotation3<f64>,
    /// The share of the object's pixels in the crop that are seen (not hidden by another object,
    /// not outside the frame).
    pub visible_fraction: f64,
}

/// Uniform in `[lo, hi)`, restricted to the even (training) or odd (held-out) ones of `bands`
/// equal bands of the range.
fn banded<R: Rng + ?Sized>(rng: &mut R, lo: f64, hi: f64, split: Split) -> f64 {
    const BANDS: usize = 6;
    let width = (hi - lo) / BANDS as f64;
    let parity = match split {
        Split::Train => 0,
        Split::HeldOut => 1,
    };
    let band = 2 * rng.random_range(0..BANDS / 2) + parity;
    lo + width * (band as f64 + rng.random::<f64>())
}

/// A standard normal draw (Box–Muller).
fn gauss<R: Rng + ?Sized>(rng: &mut R) -> f64 {
    let u: f64 = rng.random::<f64>().max(1e-12);
    let v: f64 = rng.random::<f64>();
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
}

/// A linear RGB colour of hue (banded), saturation and value in the given ranges.
fn random_colour<R: Rng + ?Sized>(
    rng: &mut R,
    split: Split,
    sat: (f64, f64),
    val: (f64, f64),
) -> [f32; 3] {
    let hue = banded(rng, 0.0, 360.0, split);
    let s = rng.random_range(sat.0..sat.1);
    let v = rng.random_range(val.0..val.1);
    let c = v * s;
    let x = c * (1.0 - ((hue / 60.0) % 2.0 - 1.0).abs());
    let (r, g, b) = match (hue / 60.0) as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    [r + m, g + m, b + m].map(|c| (c as f32).powf(GAMMA))
}

/// A random material: a base colour (white when the mesh has its own colours, which then show
/// through), roughness and metalness from the split's bands.
pub fn random_material<R: Rng + ?Sized>(rng: &mut R, split: Split, has_colours: bool) -> Material {
    let base = if has_colours {
        [1.0; 3]
    } else {
        random_colour(rng, split, (0.0, 0.9), (0.25, 1.0))
    };
    Material {
        base,
        roughness: banded(rng, 0.08, 1.0, split) as f32,
        metalness: if rng.random::<f64>() < 0.3 {
            banded(rng, 0.3, 1.0, split) as f32
        } else {
            0.0
        },
    }
}

/// 1–3 directional lights of random direction, colour and intensity, and a random ambient.
pub fn random_lighting<R: Rng + ?Sized>(rng: &mut R, split: Split) -> Lighting {
    let n = rng.random_range(1..=3);
    let lights = (0..n)
        .map(|i| {
            // The first light comes from the camera's side; the others from anywhere (rim light).
            let mut d = Vector3::new(gauss(rng), gauss(rng), gauss(rng))
                .try_normalize(1e-9)
                .unwrap_or(-Vector3::z());
            if i == 0 && d.z > 0.0 {
                d.z = -d.z;
            }
            let colour = random_colour(rng, split, (0.0, 0.4), (1.0, 1.0001));
            let intensity = banded(rng, 0.4, 2.2, split) as f32 / n as f32 * 1.5;
            Light {
                direction: d,
                radiance: colour.map(|c| c * intensity),
            }
        })
        .collect();
    let ambient_colour = random_colour(rng, split, (0.0, 0.3), (1.0, 1.0001));
    let ambient = banded(rng, 0.02, 0.5, split) as f32;
    Lighting {
        lights,
        ambient: ambient_colour.map(|c| c * ambient),
    }
}

/// Smooth value noise in `[0, 1]` at `n × n` with `octaves` octaves, the coarsest `cells` cells a
/// side.
fn value_noise<R: Rng + ?Sized>(rng: &mut R, n: usize, cells: usize, octaves: usize) -> Vec<f32> {
    let mut out = vec![0f32; n * n];
    let mut amplitude = 1.0f32;
    let mut total = 0.0f32;
    let mut c = cells.max(1);
    for _ in 0..octaves {
        let lattice: Vec<f32> = (0..(c + 1) * (c + 1))
            .map(|_| rng.random::<f32>())
            .collect();
        for y in 0..n {
            let gy = y as f32 / n as f32 * c as f32;
            let (y0, ty) = (gy.floor() as usize, gy.fract());
            let ty = ty * ty * (3.0 - 2.0 * ty);
            for x in 0..n {
                let gx = x as f32 / n as f32 * c as f32;
                let (x0, tx) = (gx.floor() as usize, gx.fract());
                let tx = tx * tx * (3.0 - 2.0 * tx);
                let at = |i: usize, j: usize| lattice[(j.min(c)) * (c + 1) + i.min(c)];
                let top = at(x0, y0) * (1.0 - tx) + at(x0 + 1, y0) * tx;
                let bottom = at(x0, y0 + 1) * (1.0 - tx) + at(x0 + 1, y0 + 1) * tx;
                out[y * n + x] += amplitude * (top * (1.0 - ty) + bottom * ty);
            }
        }
        total += amplitude;
        amplitude *= 0.5;
        c *= 2;
    }
    out.iter_mut().for_each(|v| *v /= total);
    out
}

fn mix(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    std::array::from_fn(|k| a[k] * (1.0 - t) + b[k] * t)
}

/// Share of backgrounds that are real photographs (the rest are procedural).
pub const PHOTO_SHARE: f64 = 0.4;

/// The background photographs of a split (`assets/backgrounds/`, their sources and licences in
/// `SOURCES.md` there), decoded once.
pub fn photos(split: Split) -> &'static [image::RgbImage] {
    use std::sync::OnceLock;
    static TRAIN: OnceLock<Vec<image::RgbImage>> = OnceLock::new();
    static HELD_OUT: OnceLock<Vec<image::RgbImage>> = OnceLock::new();
    const TRAIN_FILES: [&[u8]; 5] = [
        include_bytes!("../../assets/backgrounds/train/chelsea.jpg"),
        include_bytes!("../../assets/backgrounds/train/coffee.jpg"),
        include_bytes!("../../assets/backgrounds/train/brick.jpg"),
        include_bytes!("../../assets/backgrounds/train/grass.jpg"),
        include_bytes!("../../assets/backgrounds/train/camera.jpg"),
    ];
    const HELD_OUT_FILES: [&[u8]; 4] = [
        include_bytes!("../../assets/backgrounds/held_out/astronaut.jpg"),
        include_bytes!("../../assets/backgrounds/held_out/rocket.jpg"),
        include_bytes!("../../assets/backgrounds/held_out/gravel.jpg"),
        include_bytes!("../../assets/backgrounds/held_out/clock_motion.jpg"),
    ];
    let decode = |files: &[&[u8]]| {
        files
            .iter()
            .filter_map(|bytes| image::load_from_memory(bytes).ok().map(|i| i.to_rgb8()))
            .collect()
    };
    match split {
        Split::Train => TRAIN.get_or_init(|| decode(&TRAIN_FILES)),
        Split::HeldOut => HELD_OUT.get_or_init(|| decode(&HELD_OUT_FILES)),
    }
}

/// A random window of one of the split's photographs (30–100 % of its shorter side, anywhere,
/// maybe mirrored), resampled bilinearly to `n × n`, made linear and tinted.
fn photo_background<R: Rng + ?Sized>(rng: &mut R, split: Split, n: usize) -> Option<Vec<[f32; 3]>> {
    let set = photos(split);
    if set.is_empty() {
        return None;
    }
    let photo = &set[rng.random_range(0..set.len())];
    let (w, h) = (photo.width() as f32, photo.height() as f32);
    let side = w.min(h) * rng.random_range(0.3..1.0f32);
    let (x0, y0) = (
        rng.random::<f32>() * (w - side),
        rng.random::<f32>() * (h - side),
    );
    let mirror = rng.random::<f64>() < 0.5;
    let tint: [f32; 3] = std::array::from_fn(|_| rng.random_range(0.6..1.4f32));
    let gain = 2f32.powf(rng.random_range(-0.8..0.8f32));
    let scale = side / n as f32;
    Some(
        (0..n * n)
            .map(|i| {
                let (mut i_x, i_y) = ((i % n) as f32, (i / n) as f32);
                if mirror {
                    i_x = n as f32 - 1.0 - i_x;
                }
                let c = crate::cad::bilinear(
                    photo,
                    x0 + (i_x + 0.5) * scale - 0.5,
                    y0 + (i_y + 0.5) * scale - 0.5,
                    crate::cad::Edges::Clamp,
                    crate::cad::scene::srgb_to_linear,
                );
                std::array::from_fn(|k| c[k] * tint[k] * gain)
            })
            .collect(),
    )
}

/// A background, `n × n` linear RGB: a real photograph ([`PHOTO_SHARE`] of them, each split its
/// own) or a procedural texture. Training draws multi-scale noise, random shapes and lines, or
/// gradients; the held-out split draws stripes and checks, cells, or soft blobs.
pub fn background<R: Rng + ?Sized>(rng: &mut R, split: Split, n: usize) -> Vec<[f32; 3]> {
    if rng.random::<f64>() < PHOTO_SHARE
        && let Some(photo) = photo_background(rng, split, n)
    {
        return photo;
    }
    let colour = |rng: &mut R| random_colour(rng, split, (0.0, 1.0), (0.05, 1.0));
    let (a, b) = (colour(rng), colour(rng));
    let kind = rng.random_range(0..3);
    let mut out: Vec<[f32; 3]> = match (split, kind) {
        (Split::Train, 0) => {
            let cells = rng.random_range(2..8);
            let octaves = rng.random_range(2..5);
            value_noise(rng, n, cells, octaves)
                .into_iter()
                .map(|t| mix(a, b, t))
                .collect()
        }
        (Split::Train, 1) => shapes(rng, n, a, colour),
        (Split::Train, _) => gradient(rng, n, a, b),
        (Split::HeldOut, 0) => stripes(rng, n, a, b),
        (Split::HeldOut, 1) => cells(rng, n, a, colour),
        (Split::HeldOut, _) => blobs(rng, n, a, colour),
    };
    // Fine grain over every family: surfaces are never perfectly flat.
    let grain = rng.random_range(0.0..0.15f32);
    if grain > 0.0 {
        let noise = value_noise(rng, n, n / 2, 1);
        for (p, g) in out.iter_mut().zip(noise) {
            *p = p.map(|c| c * (1.0 + grain * (g - 0.5) * 2.0));
        }
    }
    out
}

type Rgb = [f32; 3];

/// Training: random rectangles, discs and lines of random colours on `a`.
fn shapes<R: Rng + ?Sized>(
    rng: &mut R,
    n: usize,
    a: Rgb,
    colour: impl Fn(&mut R) -> Rgb,
) -> Vec<Rgb> {
    let mut img = vec![a; n * n];
    for _ in 0..rng.random_range(3..16) {
        let c = colour(rng);
        let (cx, cy) = (
            rng.random::<f32>() * n as f32,
            rng.random::<f32>() * n as f32,
        );
        let r = rng.random_range(0.05..0.5) * n as f32;
        match rng.random_range(0..3) {
            0 => fill(&mut img, n, c, |x, y| {
                (x - cx).abs() < r && (y - cy).abs() < r * 0.6
            }),
            1 => fill(&mut img, n, c, |x, y| {
                (x - cx).powi(2) + (y - cy).powi(2) < r * r
            }),
            _ => {
                let angle = rng.random::<f32>() * std::f32::consts::PI;
                let (s, co) = angle.sin_cos();
                let half = rng.random_range(0.5..2.5f32);
                fill(&mut img, n, c, |x, y| {
                    ((x - cx) * s - (y - cy) * co).abs() < half
                })
            }
        }
    }
    img
}

/// Training: a linear gradient from `a` to `b` at a random angle.
fn gradient<R: Rng + ?Sized>(rng: &mut R, n: usize, a: Rgb, b: Rgb) -> Vec<Rgb> {
    let angle = rng.random::<f32>() * std::f32::consts::TAU;
    let (s, c) = angle.sin_cos();
    (0..n * n)
        .map(|i| {
            let (x, y) = (
                (i % n) as f32 / n as f32 - 0.5,
                (i / n) as f32 / n as f32 - 0.5,
            );
            mix(a, b, (x * c + y * s + 0.5).clamp(0.0, 1.0))
        })
        .collect()
}

/// Held out: stripes or checks of `a` and `b` at a random period and angle.
fn stripes<R: Rng + ?Sized>(rng: &mut R, n: usize, a: Rgb, b: Rgb) -> Vec<Rgb> {
    let period = rng.random_range(3.0..(n as f32 / 2.0).max(4.0));
    let angle = rng.random::<f32>() * std::f32::consts::PI;
    let (s, c) = angle.sin_cos();
    let check = rng.random::<f64>() < 0.5;
    (0..n * n)
        .map(|i| {
            let (x, y) = ((i % n) as f32, (i / n) as f32);
            let u = ((x * c + y * s) / period).floor() as i64;
            let v = ((-x * s + y * c) / period).floor() as i64;
            let on = if check {
                (u + v).rem_euclid(2)
            } else {
                u.rem_euclid(2)
            };
            if on == 0 { a } else { b }
        })
        .collect()
}

/// Held out: Voronoi cells of random colours.
fn cells<R: Rng + ?Sized>(
    rng: &mut R,
    n: usize,
    a: Rgb,
    colour: impl Fn(&mut R) -> Rgb,
) -> Vec<Rgb> {
    let sites: Vec<([f32; 2], [f32; 3])> = (0..rng.random_range(4..24))
        .map(|_| {
            (
                [
                    rng.random::<f32>() * n as f32,
                    rng.random::<f32>() * n as f32,
                ],
                colour(rng),
            )
        })
        .collect();
    (0..n * n)
        .map(|i| {
            let (x, y) = ((i % n) as f32, (i / n) as f32);
            sites
                .iter()
                .min_by(|p, q| {
                    let d = |s: &[f32; 2]| (s[0] - x).powi(2) + (s[1] - y).powi(2);
                    d(&p.0).total_cmp(&d(&q.0))
                })
                .map_or(a, |s| s.1)
        })
        .collect()
}

/// Held out: soft Gaussian blobs of random colours over `a`.
fn blobs<R: Rng + ?Sized>(
    rng: &mut R,
    n: usize,
    a: Rgb,
    colour: impl Fn(&mut R) -> Rgb,
) -> Vec<Rgb> {
    let blobs: Vec<([f32; 3], [f32; 3])> = (0..rng.random_range(3..10))
        .map(|_| {
            (
                [
                    rng.random::<f32>() * n as f32,
                    rng.random::<f32>() * n as f32,
                    rng.random_range(0.1..0.4) * n as f32,
                ],
                colour(rng),
            )
        })
        .collect();
    (0..n * n)
        .map(|i| {
            let (x, y) = ((i % n) as f32, (i / n) as f32);
            blobs.iter().fold(a, |acc, (p, c)| {
                let d2 = (p[0] - x).powi(2) + (p[1] - y).powi(2);
                mix(acc, *c, (-d2 / (2.0 * p[2] * p[2])).exp())
            })
        })
        .collect()
}

fn fill(img: &mut [[f32; 3]], n: usize, c: [f32; 3], inside: impl Fn(f32, f32) -> bool) {
    for (i, p) in img.iter_mut().enumerate() {
        if inside((i % n) as f32 + 0.5, (i / n) as f32 + 0.5) {
            *p = c;
        }
    }
}

/// A detector's box: each edge of `b = [x, y, w, h]` moved by a normal error of `sigma` × the
/// side it bounds, then clipped to the `width × height` frame (at least 2 pixels a side).
pub fn jitter_box<R: Rng + ?Sized>(
    rng: &mut R,
    b: [f64; 4],
    sigma: f64,
    width: u32,
    height: u32,
) -> [f64; 4] {
    let [x, y, w, h] = b;
    let (mut x0, mut y0, mut x1, mut y1) = (x, y, x + w, y + h);
    if sigma > 0.0 {
        x0 += gauss(rng) * sigma * w;
        x1 += gauss(rng) * sigma * w;
        y0 += gauss(rng) * sigma * h;
        y1 += gauss(rng) * sigma * h;
    }
    clip_box(
        [x0.min(x1), y0.min(y1), (x1 - x0).abs(), (y1 - y0).abs()],
        width,
        height,
    )
}

/// `b` clipped to the `width × height` frame, at least 2 pixels a side.
pub fn clip_box(b: [f64; 4], width: u32, height: u32) -> [f64; 4] {
    let (w, h) = (width as f64, height as f64);
    let x0 = b[0].clamp(0.0, w - 2.0);
    let y0 = b[1].clamp(0.0, h - 2.0);
    let x1 = (b[0] + b[2]).clamp(x0 + 2.0, w);
    let y1 = (b[1] + b[3]).clamp(y0 + 2.0, h);
    [x0, y0, x1 - x0, y1 - y0]
}

/// The camera model on a linear `size × size` image: exposure, white balance, saturation, gamma,
/// optional blur, sensor noise and JPEG compression, to RGB8.
pub fn camera_effects<R: Rng + ?Sized>(
    rng: &mut R,
    split: Split,
    linear: &[[f32; 3]],
    size: usize,
) -> Vec<u8> {
    let exposure = 2f32.powf(banded(rng, -1.0, 1.0, split) as f32);
    let balance: [f32; 3] = std::array::from_fn(|_| rng.random_range(0.85..1.15f32));
    let saturation = rng.random_range(0.6..1.4f32);
    let gamma = GAMMA * banded(rng, 0.8, 1.2, split) as f32;
    let mut img: Vec<[f32; 3]> = linear
        .iter()
        .map(|p| {
            let c: [f32; 3] =
                std::array::from_fn(|k| (p[k] * exposure * balance[k]).clamp(0.0, 1.0));
            let luma = 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2];
            c.map(|v| {
                (luma + (v - luma) * saturation)
                    .clamp(0.0, 1.0)
                    .powf(1.0 / gamma)
            })
        })
        .collect();
    if rng.random::<f64>() < 0.4 {
        let sigma = banded(rng, 0.3, 1.3, split) as f32;
        img = gaussian_blur(&img, size, sigma);
    }
    let read = banded(rng, 0.0, 0.06, split) as f32;
    let shot = rng.random_range(0.0..0.04f32);
    let mut rgb: Vec<u8> = img
        .iter()
        .flat_map(|p| {
            p.map(|v| {
                let s = (read * read + shot * shot * v).sqrt();
                ((v + s * gauss(rng) as f32) * 255.0)
                    .round()
                    .clamp(0.0, 255.0) as u8
            })
        })
        .collect();
    if rng.random::<f64>() < 0.5 {
        let quality = banded(rng, 20.0, 95.0, split) as u8;
        rgb = jpeg_round_trip(&rgb, size as u32, quality).unwrap_or(rgb);
    }
    rgb
}

/// A linear image to RGB8 through the display gamma alone (the neutral camera).
fn plain_camera(linear: &[[f32; 3]]) -> Vec<u8> {
    linear
        .iter()
        .flat_map(|p| p.map(|v| (v.clamp(0.0, 1.0).powf(1.0 / GAMMA) * 255.0).round() as u8))
        .collect()
}

/// A separable Gaussian blur with standard deviation `sigma` pixels (edges clamped).
fn gaussian_blur(img: &[[f32; 3]], n: usize, sigma: f32) -> Vec<[f32; 3]> {
    let radius = (2.5 * sigma).ceil() as i64;
    let kernel: Vec<f32> = (-radius..=radius)
        .map(|d| (-(d * d) as f32 / (2.0 * sigma * sigma)).exp())
        .collect();
    let total: f32 = kernel.iter().sum();
    let pass = |src: &[[f32; 3]], horizontal: bool| -> Vec<[f32; 3]> {
        (0..n * n)
            .map(|i| {
                let (x, y) = ((i % n) as i64, (i / n) as i64);
                let mut acc = [0f32; 3];
                for (j, w) in kernel.iter().enumerate() {
                    let d = j as i64 - radius;
                    let (sx, sy) = if horizontal { (x + d, y) } else { (x, y + d) };
                    let p = src[(sy.clamp(0, n as i64 - 1) * n as i64 + sx.clamp(0, n as i64 - 1))
                        as usize];
                    for k in 0..3 {
                        acc[k] += w * p[k];
                    }
                }
                acc.map(|v| v / total)
            })
            .collect()
    };
    pass(&pass(img, true), false)
}

/// Encodes RGB8 as JPEG at `quality` and decodes it again (its block and ringing artefacts).
fn jpeg_round_trip(rgb: &[u8], size: u32, quality: u8) -> Option<Vec<u8>> {
    let mut bytes = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, quality.clamp(1, 100))
        .encode(rgb, size, size, image::ExtendedColorType::Rgb8)
        .ok()?;
    let decoded = image::load_from_memory_with_format(&bytes, image::ImageFormat::Jpeg).ok()?;
    Some(decoded.to_rgb8().into_raw())
}

/// Where the subject sits in the frame: a Haar-random rotation at a distance in
/// [`FRAME_DISTANCE`], anywhere its whole sphere fits, or (with the realism's truncation chance)
/// its centre anywhere in the frame, so the edge may cut up to about half.
fn placement<R: Rng + ?Sized>(rng: &mut R, camera: &Camera, truncation: f64) -> Pose {
    let rotation = haar_rotation(rng);
    let z = rng.random_range(FRAME_DISTANCE.0..FRAME_DISTANCE.1);
    let cut = rng.random::<f64>() < truncation;
    Pose {
        rotation,
        ..placement_at_depth(camera, z, !cut, rng)
    }
}

/// A realistic crop of object `object` of `assets`, `size` pixels a side, rendered at
/// `size · supersample` and averaged down, everything drawn from `rng`.
pub fn realistic_crop<R: Rng + ?Sized>(
    assets: &SceneAssets,
    object: usize,
    size: u32,
    supersample: u32,
    rng: &mut R,
) -> RealisticCrop {
    let realism = &assets.realism;
    let split = realism.split;
    let camera = frame_camera();
    let k = camera.k();
    let ss = supersample.max(1);
    let big_size = size * ss;
    let n = big_size as usize;
    let mesh = &assets.meshes[object];
    loop {
        let pose = placement(rng, &camera, realism.truncation);
        let exact = clip_box(
            object_box(mesh, &pose, &camera),
            camera.width,
            camera.height,
        );
        let sigma = realism.draw_box_sigma(rng);
        let bbox = jitter_box(rng, exact, sigma, camera.width, camera.height);
        let (Some(view), Some(big)) = (
            VirtualCamera::looking_at(&k, bbox, size),
            VirtualCamera::looking_at(&k, bbox, big_size),
        ) else {
            continue;
        };
        let subject = big.pose_in_virtual(&pose);
        let neutral = realism.neutral;
        let (material, lighting) = neutral.draw_look(rng, split, mesh.colors.is_some());
        let mut objects = vec![SceneObject {
            mesh,
            normals: &assets.normals[object],
            pose: subject,
            material,
        }];
        let cluttered = rng.random::<f64>() < realism.clutter;
        if cluttered {
            add_background_objects(rng, assets, &big.camera, &subject, split, &mut objects);
        }
        let occluder = (cluttered && rng.random::<f64>() < 0.5)
            .then(|| occluder_candidate(rng, assets, &subject, split))
            .flatten();
        // The scene is drawn once; each place the occluder is tried draws only the occluder on
        // a copy, and the scene kept is shaded once.
        let mut raster = SceneRaster::of(&objects, &big.camera);
        if let Some((mut occluder, placement)) = occluder {
            // Pushed outwards until at most about half of the subject is hidden.
            for step in 0..4 {
                occluder.pose.translation = placement.position(&subject, 1.0 + 0.3 * step as f64);
                let mut candidate = raster.clone();
                candidate.draw(occluder, &big.camera);
                if candidate.visible_fraction() >= 0.5 {
                    raster = candidate;
                    break;
                }
            }
        }
        let mut scene = raster.shade(&big.camera, &lighting);
        let unoccluded = scene.unoccluded_pixels;
        // Pixels whose ray leaves the real frame are black, as a server's crop of a frame is.
        let h = big.homography(&k);
        let mut back = neutral.draw_background(rng, split, n).into_iter();
        let mut linear = Vec::with_capacity(n * n);
        for (idx, seen) in scene.linear.iter().enumerate() {
            let bg = back.next().unwrap_or([0.0; 3]);
            let p = h * Vector3::new((idx % n) as f64 + 0.5, (idx / n) as f64 + 0.5, 1.0);
            let (u, v) = (p.x / p.z, p.y / p.z);
            let inside = p.z > 0.0
                && (0.0..camera.width as f64).contains(&u)
                && (0.0..camera.height as f64).contains(&v);
            if !inside {
                linear.push([0.0; 3]);
                scene.subject.mask[idx] = false;
                scene.subject.depth[idx] = 0.0;
                scene.subject.nocs[idx] = [f32::NAN; 3];
            } else {
                linear.push(seen.unwrap_or(bg));
            }
        }
        let seen = scene.subject.mask_area();
        if seen < 4 || unoccluded == 0 {
            continue;
        }
        let small = box_filter_linear(&linear, n, ss as usize);
        let rgb = neutral.draw_camera(rng, split, &small, size as usize);
        return RealisticCrop {
            rgb,
            render: scene.subject,
            r_virtual: view.pose_in_virtual(&pose).rotation,
            visible_fraction: seen as f64 / unoccluded as f64,
        };
    }
}

/// Up to three distractors behind the subject, somewhere in the crop's view.
fn add_background_objects<'a, R: Rng + ?Sized>(
    rng: &mut R,
    assets: &'a SceneAssets,
    camera: &Camera,
    subject: &Pose,
    split: Split,
    objects: &mut Vec<SceneObject<'a>>,
) {
    let tan_half = camera.width as f64 / 2.0 / camera.fx;
    let z0 = subject.translation.z;
    for _ in 0..rng.random_range(1..=3) {
        let (mesh, normals) = &assets.distractors[rng.random_range(0..assets.distractors.len())];
        let z = z0 + rng.random_range(2.2..8.0);
        let spread = 1.3 * tan_half * z;
        objects.push(SceneObject {
            mesh,
            normals,
            pose: Pose {
                rotation: haar_rotation(rng),
                translation: Vector3::new(
                    rng.random_range(-spread..spread),
                    rng.random_range(-spread..spread),
                    z,
                ),
            },
            material: random_material(rng, split, mesh.colors.is_some()),
        });
    }
}

/// Where an occluder goes: `depth` along the subject's line of sight, moved sideways in
/// `direction` by `reach` × the sum of both objects' angular radii.
#[derive(Debug, Clone, Copy)]
struct OccluderPlacement {
    direction: [f64; 2],
    reach: f64,
    depth: f64,
}

impl OccluderPlacement {
    /// The occluder's centre in the camera frame, its reach scaled by `scale`.
    fn position(&self, subject: &Pose, scale: f64) -> Vector3<f64> {
        let t = subject.translation;
        let z0 = t.norm();
        let radii = (1.0 / z0).asin() + (1.0 / self.depth).min(1.0).asin();
        let axis = t / z0;
        let side = axis
            .cross(&Vector3::y())
            .try_normalize(1e-9)
            .unwrap_or(Vector3::x());
        let up = axis.cross(&side);
        let sideways = side * self.direction[0] + up * self.direction[1];
        (axis + sideways * (self.reach * scale * radii.tan())).normalize() * self.depth
    }
}

/// A distractor between the camera and the subject and where it goes; `None` when the subject
/// is too near the camera for one.
fn occluder_candidate<'a, R: Rng + ?Sized>(
    rng: &mut R,
    assets: &'a SceneAssets,
    subject: &Pose,
    split: Split,
) -> Option<(SceneObject<'a>, OccluderPlacement)> {
    let z0 = subject.translation.norm();
    let (near, far) = (1.4, z0 - 2.2);
    if near >= far {
        return None;
    }
    let depth = rng.random_range(near..far);
    let (mesh, normals) = &assets.distractors[rng.random_range(0..assets.distractors.len())];
    let angle = rng.random::<f64>() * std::f64::consts::TAU;
    let placement = OccluderPlacement {
        direction: [angle.cos(), angle.sin()],
        reach: rng.random_range(0.55..0.95),
        depth,
    };
    let occluder = SceneObject {
        mesh,
        normals,
        pose: Pose {
            rotation: haar_rotation(rng),
            translation: Vector3::zeros(),
        },
        material: random_material(rng, split, mesh.colors.is_some()),
    };
    Some((occluder, placement))
}

/// Averages `ss × ss` blocks of a linear image of side `big`.
fn box_filter_linear(img: &[[f32; 3]], big: usize, ss: usize) -> Vec<[f32; 3]> {
    let n = big / ss;
    let area = (ss * ss) as f32;
    (0..n * n)
        .map(|i| {
            let (x, y) = (i % n, i / n);
            let mut acc = [0f32; 3];
            for dy in 0..ss {
                for dx in 0..ss {
                    let p = img[(y * ss + dy) * big + x * ss + dx];
                    for k in 0..3 {
                        acc[k] += p[k];
                    }
                }
            }
            acc.map(|v| v / area)
        })
        .collect()
}
