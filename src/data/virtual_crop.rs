//! Object crops as a virtual camera sees them (docs/DESIGN.md §1, "Crops and cameras"), rendered
//! directly — fresh training and evaluation data.
//!
//! The crop convention, shared by training, evaluation and serving: given the camera's
//! intrinsics `K` and the object's box `(x, y, w, h)` in pixels, a virtual camera with the same
//! centre looks along the ray through the box centre (`R_ray` turns the optical axis onto that
//! ray); its image is a square of `size` pixels whose side spans [`CROP_MARGIN`] × the box's
//! longer side (focal length `f_virtual = f · size / (CROP_MARGIN · max(w, h))`), so the crop is
//! never stretched. The network answers `R_virtual`; the camera-frame rotation is
//! `R_cam = R_ray · R_virtual`.
//!
//! Two cameras with one centre see images related by a homography, so the crop of a full image
//! (a warp, for callers with a full frame) and a render made directly in the virtual camera (for
//! training data) are the same picture but for resampling. Fresh renders place the object at a
//! random position and distance in a [`FRAME_WIDTH`] × [`FRAME_HEIGHT`] frame, take its box from
//! the projected mesh (BOP's `bbox_obj`), and render the virtual camera's view at
//! `size × supersample`, box-filtered down (anti-aliased).

use nalgebra::{Matrix3, Rotation3, Unit, Vector3};
use rand::{Rng, RngExt};

use crate::cad::{Camera, Mesh, Pose, Render, RenderOptions, render};
use crate::so3::haar_rotation;

/// The crop's side over the box's longer side.
pub const CROP_MARGIN: f64 = 1.2;

/// Width of the frame fresh renders are placed in.
pub const FRAME_WIDTH: u32 = 640;
/// Height of the frame fresh renders are placed in.
pub const FRAME_HEIGHT: u32 = 480;
/// Focal length of that frame, in pixels (a 64° horizontal field of view).
pub const FRAME_FOCAL: f64 = 500.0;
/// Range of the object's distance in fresh renders, in bounding-sphere radii.
pub const FRAME_DISTANCE: (f64, f64) = (3.0, 8.0);

/// The camera of the frame fresh renders are placed in.
pub fn frame_camera() -> Camera {
    frame_camera_of(FRAME_WIDTH, FRAME_HEIGHT)
}

/// A `width × height` camera with the principal point at the centre and the field of view of
/// [`frame_camera`] (focal length `FRAME_FOCAL · width / FRAME_WIDTH`).
pub fn frame_camera_of(width: u32, height: u32) -> Camera {
    let f = FRAME_FOCAL * width as f64 / FRAME_WIDTH as f64;
    Camera {
        fx: f,
        fy: f,
        cx: width as f64 / 2.0,
        cy: height as f64 / 2.0,
        width,
        height,
    }
}

/// A virtual camera looking at a box: its rotation from the real camera and its intrinsics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VirtualCamera {
    /// `R_ray`: turns the real camera's optical axis onto the ray through the box centre
    /// (`x_cam = R_ray · x_virtual`); the rotation of least angle that does so.
    pub r_ray: Rotation3<f64>,
    /// Intrinsics and size of the crop.
    pub camera: Camera,
}

impl VirtualCamera {
    /// The virtual camera of the crop of `bbox = (x, y, w, h)` (pixels of a camera with
    /// intrinsics `k`, row-major) at `size × size` pixels. `None` for a box with no area or
    /// non-finite values, or intrinsics without positive focal lengths.
    pub fn looking_at(k: &[f64; 9], bbox: [f64; 4], size: u32) -> Option<VirtualCamera> {
        let (fx, fy, cx, cy) = (k[0], k[4], k[2], k[5]);
        let [x, y, w, h] = bbox;
        let finite = bbox.iter().chain(k).all(|v| v.is_finite());
        let positive = fx > 0.0 && fy > 0.0 && w > 0.0 && h > 0.0 && size > 0;
        if !(finite && positive) {
            return None;
        }
        // The ray through the box centre, in the real camera.
        let (u, v) = (x + w / 2.0, y + h / 2.0);
        let ray = Vector3::new((u - cx) / fx, (v - cy) / fy, 1.0).normalize();
        let z = Vector3::z();
        let axis = z.cross(&ray);
        let r_ray = if axis.norm() < 1e-12 {
            Rotation3::identity()
        } else {
            Rotation3::from_axis_angle(
                &Unit::new_normalize(axis),
                ray.dot(&z).clamp(-1.0, 1.0).acos(),
            )
        };
        // The box's longer side in units of the focal length, spread over the crop.
        let extent = CROP_MARGIN * (w / fx).max(h / fy);
        let f = size as f64 / extent;
        Some(VirtualCamera {
            r_ray,
            camera: Camera::square_with_focal(size, f),
        })
    }

    /// The pose in the virtual camera of an object at `pose` in the real one:
    /// `R_virtual = R_rayᵀ·R_cam`, `t_virtual = R_rayᵀ·t`.
    pub fn pose_in_virtual(&self, pose: &Pose) -> Pose {
        let back = self.r_ray.inverse();
        Pose {
            rotation: back * pose.rotation,
            translation: back * pose.translation,
        }
    }

    /// The homography from crop pixels to real-camera pixels: `K · R_ray · K_virtual⁻¹`.
    pub fn homography(&self, k: &[f64; 9]) -> Matrix3<f64> {
        let k_real = Matrix3::from_row_slice(k);
        let c = &self.camera;
        let k_virtual_inv = Matrix3::new(
            1.0 / c.fx,
            0.0,
            -c.cx / c.fx,
            0.0,
            1.0 / c.fy,
            -c.cy / c.fy,
            0.0,
            0.0,
            1.0,
        );
        k_real * self.r_ray.matrix() * k_virtual_inv
    }
}

/// The box of the projected mesh (BOP's `bbox_obj`) `(x, y, w, h)` in pixels of `camera`.
pub fn object_box(mesh: &Mesh, pose: &Pose, camera: &Camera) -> [f64; 4] {
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for v in &mesh.vertices {
        let p = pose.rotation * v.cast::<f64>() + pose.translation;
        let (u, w) = camera.project(&p);
        lo = [lo[0].min(u), lo[1].min(w)];
        hi = [hi[0].max(u), hi[1].max(w)];
    }
    [lo[0], lo[1], hi[0] - lo[0], hi[1] - lo[1]]
}

/// A random placement of a NOCS object in the frame of [`frame_camera`]: a Haar-random
/// rotation and [`random_placement_in`] that frame.
pub fn random_placement<R: Rng + ?Sized>(rng: &mut R) -> Pose {
    let rotation = haar_rotation(rng);
    Pose {
        rotation,
        ..random_placement_in(&frame_camera(), rng)
    }
}

/// [`object_box`] rounded out to whole pixels and clipped to the image: `[x, y, width, height]`,
/// as a detector would give it.
pub fn object_pixel_box(mesh: &Mesh, pose: &Pose, camera: &Camera) -> [u32; 4] {
    let b = object_box(mesh, pose, camera);
    let (x, y) = (b[0].floor().max(0.0), b[1].floor().max(0.0));
    let right = (b[0] + b[2]).ceil().min(camera.width as f64);
    let bottom = (b[1] + b[3]).ceil().min(camera.height as f64);
    [x as u32, y as u32, (right - x) as u32, (bottom - y) as u32]
}

/// A random position of a NOCS object (radius 1) in `camera`'s frame, the identity rotation: a
/// distance in [`FRAME_DISTANCE`] and a centre whose projection lies at least the projected
/// sphere's radius from every edge, so the whole object is in the frame.
pub fn random_placement_in<R: Rng + ?Sized>(camera: &Camera, rng: &mut R) -> Pose {
    let z = rng.random_range(FRAME_DISTANCE.0..FRAME_DISTANCE.1);
    placement_at_depth(camera, z, true, rng)
}

/// A random position at distance `z` of a NOCS object (radius 1) in `camera`'s frame, the
/// identity rotation: its centre's projection at least the projected sphere's radius from every
/// edge when `whole` (the whole object in the frame), else anywhere in the frame (the edge may
/// cut up to about half of it).
pub fn placement_at_depth<R: Rng + ?Sized>(
    camera: &Camera,
    z: f64,
    whole: bool,
    rng: &mut R,
) -> Pose {
    let r_px = camera.fx.max(camera.fy) / (z * z - 1.0).sqrt();
    let mut span = |extent: f64| {
        let (lo, hi) = if whole {
            (r_px, extent - r_px)
        } else {
            (0.0, extent)
        };
        if lo < hi {
            rng.random_range(lo..hi)
        } else {
            extent / 2.0
        }
    };
    let (u, v) = (span(camera.width as f64), span(camera.height as f64));
    Pose {
        rotation: Rotation3::identity(),
        translation: Vector3::new(
            (u - camera.cx) / camera.fx * z,
            (v - camera.cy) / camera.fy * z,
            z,
        ),
    }
}

/// A rendered crop.
pub struct RenderedCrop {
    /// `size² × 3` RGB8, anti-aliased.
    pub rgb: Vec<u8>,
    /// The virtual camera's render at `size · supersample` (mask, NOCS, depth).
    pub render: Render,
    /// The camera of `render` (the virtual camera at `size · supersample` pixels).
    pub render_camera: Camera,
    /// The object's rotation in the virtual camera, the network's label.
    pub r_virtual: Rotation3<f64>,
    /// The object's translation in the virtual camera (`x = R_virtual·x_nocs + t`).
    pub t_virtual: Vector3<f64>,
    /// The virtual camera.
    pub view: VirtualCamera,
}

/// Renders the crop of `mesh` (NOCS) placed at `pose` in `camera`: the virtual camera of its
/// box, `size` pixels a side, supersampled `supersample`× per axis and box-filtered.
pub fn render_crop(
    mesh: &Mesh,
    pose: &Pose,
    camera: &Camera,
    size: u32,
    supersample: u32,
    options: &RenderOptions,
) -> RenderedCrop {
    let ss = supersample.max(1);
    let bbox = object_box(mesh, pose, camera);
    let view = VirtualCamera::looking_at(&camera.k(), bbox, size)
        .expect("a mesh in front of the camera has a box with area");
    let big = VirtualCamera::looking_at(&camera.k(), bbox, size * ss)
        .expect("a mesh in front of the camera has a box with area");
    let in_view = big.pose_in_virtual(pose);
    // The light is fixed in the real camera's frame: seen from the virtual camera it turns too.
    let options = RenderOptions {
        light: big.r_ray.inverse() * options.light,
        ..*options
    };
    let render = render(mesh, &big.camera, &in_view, &options);
    RenderedCrop {
        rgb: box_filter(&render.rgb, (size * ss) as usize, ss as usize),
        render,
        render_camera: big.camera,
        r_virtual: in_view.rotation,
        t_virtual: in_view.translation,
        view,
    }
}

/// Averages `ss × ss` blocks of an RGB8 image of side `big` (a multiple of `ss`).
pub fn box_filter(rgb: &[u8], big: usize, ss: usize) -> Vec<u8> {
    let n = big / ss;
    let area = (ss * ss) as u32;
    let mut out = vec![0u8; n * n * 3];
    for y in 0..n {
        for x in 0..n {
            for c in 0..3 {
                let mut sum = 0u32;
                for dy in 0..ss {
                    let row = (y * ss + dy) * big;
                    for dx in 0..ss {
                        sum += rgb[(row + x * ss + dx) * 3 + c] as u32;
                    }
                }
                out[(y * n + x) * 3 + c] = ((sum + area / 2) / area) as u8;
            }
        }
    }
    out
}

/// The crop of a full RGB8 image (`width × height`, intrinsics `k`) as the virtual camera of
/// `bbox` sees it, `size` pixels a side, black outside the image. `None` where
/// [`VirtualCamera::looking_at`] refuses the box or the intrinsics.
///
/// Anti-aliased like the training renders: when one crop pixel covers `s > 1` image pixels, the
/// warp samples (bilinearly) a grid `ceil(s)` times finer (at most 8) and box-filters it down.
pub fn perspective_crop(
    rgb: &[u8],
    width: u32,
    height: u32,
    k: &[f64; 9],
    bbox: [f64; 4],
    size: u32,
) -> Option<(Vec<u8>, VirtualCamera)> {
    let view = VirtualCamera::looking_at(k, bbox, size)?;
    // Image pixels per crop pixel, along the box's longer side.
    let scale = CROP_MARGIN * bbox[2].max(bbox[3]) / size as f64;
    let ss = (scale.ceil() as u32).clamp(1, 8);
    if ss == 1 {
        return Some((warp(rgb, width, height, k, &view, size), view));
    }
    let fine = VirtualCamera::looking_at(k, bbox, size * ss)?;
    let big = warp(rgb, width, height, k, &fine, size * ss);
    Some((box_filter(&big, (size * ss) as usize, ss as usize), view))
}

/// Bilinear samples of the image at the homography image of every pixel of `view`'s crop.
fn warp(
    rgb: &[u8],
    width: u32,
    height: u32,
    k: &[f64; 9],
    view: &VirtualCamera,
    size: u32,
) -> Vec<u8> {
    let h = view.homography(k);
    let (w_px, h_px) = (width as i64, height as i64);
    let at = |x: i64, y: i64, c: usize| -> f64 {
        if x < 0 || y < 0 || x >= w_px || y >= h_px {
            0.0
        } else {
            rgb[((y * w_px + x) as usize) * 3 + c] as f64
        }
    };
    let n = size as usize;
    let mut out = vec![0u8; n * n * 3];
    for j in 0..n {
        for i in 0..n {
            // Pixel centres: crop (i + ½, j + ½) → image (u, v), whose pixel centres are at +½.
            let p = h * Vector3::new(i as f64 + 0.5, j as f64 + 0.5, 1.0);
            if p.z <= 0.0 {
                continue;
            }
            let (sx, sy) = (p.x / p.z - 0.5, p.y / p.z - 0.5);
            let (x0, y0) = (sx.floor() as i64, sy.floor() as i64);
            let (ax, ay) = (sx - x0 as f64, sy - y0 as f64);
            for c in 0..3 {
                let v = at(x0, y0, c) * (1.0 - ax) * (1.0 - ay)
                    + at(x0 + 1, y0, c) * ax * (1.0 - ay)
                    + at(x0, y0 + 1, c) * (1.0 - ax) * ay
                    + at(x0 + 1, y0 + 1, c) * ax * ay;
                out[(j * n + i) * 3 + c] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    out
}
