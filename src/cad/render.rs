//! A z-buffer rasteriser: pinhole camera `K`, pose `(R, t)` with `x_cam = R·x_obj + t`
//! (OpenCV camera: x right, y down, z forward), flat Lambertian + ambient shading from a light
//! fixed in the camera frame, per-face colours, a background colour.
//!
//! Outputs RGB8, the mask, depth (in the units of `t`, metres when the mesh is in metres) and the
//! NOCS map (the object coordinates of the surface point seen at each pixel, perspective-correct).
//! Pixel `(u, v)` covers `[u, u+1) × [v, v+1)` and is sampled at its centre.

use nalgebra::{Matrix3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};

use super::Mesh;

/// Depth in front of the camera plane below which a triangle's vertex skips the triangle.
pub(crate) const NEAR: f64 = 1e-6;

/// A pinhole camera with an image size.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    /// Focal length in pixels along x.
    pub fx: f64,
    /// Focal length in pixels along y.
    pub fy: f64,
    /// Principal point x in pixels.
    pub cx: f64,
    /// Principal point y in pixels.
    pub cy: f64,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

impl Camera {
    /// A square `size × size` camera with focal length `size` pixels (a 53° field of view) and
    /// the principal point at the image centre.
    pub fn square(size: u32) -> Camera {
        Camera::square_with_focal(size, size as f64)
    }

    /// A square `size × size` camera with focal length `focal` pixels and the principal point at
    /// the image centre.
    pub fn square_with_focal(size: u32, focal: f64) -> Camera {
        Camera {
            fx: focal,
            fy: focal,
            cx: size as f64 / 2.0,
            cy: size as f64 / 2.0,
            width: size,
            height: size,
        }
    }

    /// `K` row-major, as BOP's `cam_K`.
    pub fn k(&self) -> [f64; 9] {
        [self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0]
    }

    /// Projects a camera-frame point to pixel coordinates.
    pub fn project(&self, p: &Vector3<f64>) -> (f64, f64) {
        (self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy)
    }
}

/// An object pose: `x_cam = rotation · x_obj + translation`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// `R`, object to camera.
    pub rotation: Rotation3<f64>,
    /// `t`, the object origin in the camera frame.
    pub translation: Vector3<f64>,
}

/// Shading and background.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderOptions {
    /// Background colour.
    pub background: [u8; 3],
    /// Unit direction towards the light, in the camera frame.
    pub light: Vector3<f64>,
    /// Ambient fraction of the light (0 ..= 1).
    pub ambient: f64,
    /// Colour of faces of a mesh without colours.
    pub default_color: [u8; 3],
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            background: [0, 0, 0],
            light: Vector3::new(-0.4, -0.6, -1.0).normalize(),
            ambient: 0.3,
            default_color: [200, 200, 200],
        }
    }
}

/// The images of one render, row-major, `width × height`.
#[derive(Debug, Clone, PartialEq)]
pub struct Render {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// RGB8, 3 bytes per pixel.
    pub rgb: Vec<u8>,
    /// True where the object is seen.
    pub mask: Vec<bool>,
    /// Depth along the optical axis; 0 where the object is not seen.
    pub depth: Vec<f32>,
    /// Object coordinates of the surface point seen; NaN where the object is not seen.
    pub nocs: Vec<[f32; 3]>,
}

impl Render {
    /// Number of object pixels.
    pub fn mask_area(&self) -> usize {
        self.mask.iter().filter(|&&m| m).count()
    }
}

/// Renders `mesh` at `pose` through `camera`. Triangles with a vertex closer than `1e-6` to the
/// camera plane are skipped (objects are expected in front of the camera).
pub fn render(mesh: &Mesh, camera: &Camera, pose: &Pose, options: &RenderOptions) -> Render {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let rot: Matrix3<f64> = *pose.rotation.matrix();
    let cam: Vec<Vector3<f64>> = mesh
        .vertices
        .iter()
        .map(|v| rot * v.cast::<f64>() + pose.translation)
        .collect();
    let screen: Vec<(f64, f64)> = cam.iter().map(|p| camera.project(p)).collect();
    let mut raster = Raster::new(w, h);
    raster.draw_mesh(mesh, 0, &cam, &screen, false);
    let face_rgb: Vec<[u8; 3]> = (0..mesh.triangles.len())
        .map(|f| {
            let centroid = mesh.triangles[f]
                .iter()
                .map(|&i| cam[i as usize])
                .sum::<Vector3<f64>>()
                / 3.0;
            shade(mesh, f, &rot, &centroid, options)
        })
        .collect();
    let mut rgb = Vec::with_capacity(w * h * 3);
    let mut mask = Vec::with_capacity(w * h);
    let mut depth = Vec::with_capacity(w * h);
    for idx in 0..w * h {
        let f = raster.face_at[idx];
        if f == u32::MAX {
            rgb.extend_from_slice(&options.background);
            mask.push(false);
            depth.push(0.0);
        } else {
            rgb.extend_from_slice(&face_rgb[f as usize]);
            mask.push(true);
            depth.push(raster.zbuf[idx] as f32);
        }
    }
    Render {
        width: camera.width,
        height: camera.height,
        rgb,
        mask,
        depth,
        nocs: raster.nocs,
    }
}

/// The z-buffer of a render: per pixel the nearest depth, its object, its face, the
/// perspective-correct barycentric weights of the point seen and its object coordinates.
#[derive(Clone)]
pub(crate) struct Raster {
    pub(crate) width: usize,
    pub(crate) height: usize,
    pub(crate) zbuf: Vec<f64>,
    pub(crate) object_at: Vec<u16>,
    pub(crate) face_at: Vec<u32>,
    pub(crate) bary: Vec<[f32; 3]>,
    pub(crate) nocs: Vec<[f32; 3]>,
}

impl Raster {
    /// An empty `width × height` buffer.
    pub(crate) fn new(width: usize, height: usize) -> Raster {
        let n = width * height;
        Raster {
            width,
            height,
            zbuf: vec![f64::INFINITY; n],
            object_at: vec![u16::MAX; n],
            face_at: vec![u32::MAX; n],
            bary: vec![[0.0; 3]; n],
            nocs: vec![[f32::NAN; 3]; n],
        }
    }

    /// Draws every face of `mesh` as object `object` (vertices `cam` in the camera frame,
    /// `screen` projected); with `cull_back_faces` (a closed, outward-wound mesh seen from
    /// outside) only the faces turned towards the camera.
    pub(crate) fn draw_mesh(
        &mut self,
        mesh: &Mesh,
        object: u16,
        cam: &[Vector3<f64>],
        screen: &[(f64, f64)],
        cull_back_faces: bool,
    ) {
        for f in 0..mesh.triangles.len() {
            if cull_back_faces {
                // Outward winding: a face turned away from the camera (at the origin) has its
                // normal along the ray to it.
                let [a, b, c] = mesh.triangles[f].map(|i| cam[i as usize]);
                if (b - a).cross(&(c - a)).dot(&a) >= 0.0 {
                    continue;
                }
            }
            self.draw_triangle(mesh, object, f, cam, screen);
        }
    }

    /// Draws face `f` of `mesh` (vertices `cam` in the camera frame, `screen` projected) into the
    /// buffer: every pixel centre inside it that is nearer than what the buffer holds.
    fn draw_triangle(
        &mut self,
        mesh: &Mesh,
        object: u16,
        f: usize,
        cam: &[Vector3<f64>],
        screen: &[(f64, f64)],
    ) {
        let (w, h) = (self.width, self.height);
        let [i0, i1, i2] = mesh.triangles[f].map(|i| i as usize);
        let (z0, z1, z2) = (cam[i0].z, cam[i1].z, cam[i2].z);
        if z0 <= NEAR || z1 <= NEAR || z2 <= NEAR {
            return;
        }
        let (p0, p1, p2) = (screen[i0], screen[i1], screen[i2]);
        let area = edge(p0, p1, p2);
        if area.abs() < 1e-12 {
            return;
        }
        let min_y = floor_at_zero(p0.1.min(p1.1).min(p2.1));
        let max_y = ceil_within(p0.1.max(p1.1).max(p2.1), h);
        let (o0, o1, o2) = (
            mesh.vertices[i0].cast::<f64>(),
            mesh.vertices[i1].cast::<f64>(),
            mesh.vertices[i2].cast::<f64>(),
        );
        let box_x0 = floor_at_zero(p0.0.min(p1.0).min(p2.0));
        let box_x1 = ceil_within(p0.0.max(p1.0).max(p2.0), w);
        for y in min_y..max_y {
            // Wide triangles (long, thin fans) scan only their span on this row, widened by a
            // pixel; the edge tests below decide coverage either way.
            let (min_x, max_x) = if box_x1 - box_x0.min(box_x1) > 8 {
                let Some((x0, x1)) = row_span([p0, p1, p2], y as f64 + 0.5) else {
                    continue;
                };
                (
                    floor_at_zero(x0 - 1.0).max(box_x0),
                    ceil_within(x1 + 1.0, w).min(box_x1),
                )
            } else {
                (box_x0, box_x1)
            };
            for x in min_x..max_x {
                let p = (x as f64 + 0.5, y as f64 + 0.5);
                // Coverage from the edge functions' signs against the area's; the divisions
                // only for covered pixels.
                let (e0, e1, e2) = (edge(p1, p2, p), edge(p2, p0, p), edge(p0, p1, p));
                if e0 * area < 0.0 || e1 * area < 0.0 || e2 * area < 0.0 {
                    continue;
                }
                let (b0, b1, b2) = (e0 / area, e1 / area, e2 / area);
                // Perspective-correct interpolation: 1/z is affine in screen space.
                let inv_z = b0 / z0 + b1 / z1 + b2 / z2;
                let z = 1.0 / inv_z;
                let idx = y * w + x;
                if z < self.zbuf[idx] {
                    self.zbuf[idx] = z;
                    self.object_at[idx] = object;
                    self.face_at[idx] = f as u32;
                    let weights = [b0 / z0 * z, b1 / z1 * z, b2 / z2 * z];
                    self.bary[idx] = weights.map(|b| b as f32);
                    let obj = o0 * weights[0] + o1 * weights[1] + o2 * weights[2];
                    self.nocs[idx] = [obj.x as f32, obj.y as f32, obj.z as f32];
                }
            }
        }
    }
}

/// `⌊x⌋`, 0 below 0 (and for NaN): the cast truncates towards zero and saturates, so no call
/// to libm's `floor` (which the baseline x86-64 target makes for `f64::floor`, once per
/// triangle corner in the hot loop).
#[inline]
fn floor_at_zero(x: f64) -> usize {
    x as usize
}

/// `⌈x⌉` clamped to `0..=hi` (0 for NaN), without libm's `ceil`.
#[inline]
fn ceil_within(x: f64, hi: usize) -> usize {
    let t = x as i64;
    t.saturating_add(i64::from(x > t as f64))
        .clamp(0, hi as i64) as usize
}

/// Where the horizontal line at `y` crosses the triangle: `(x_min, x_max)`, or `None`.
fn row_span(p: [(f64, f64); 3], y: f64) -> Option<(f64, f64)> {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for k in 0..3 {
        let (a, b) = (p[k], p[(k + 1) % 3]);
        if (a.1 <= y && y <= b.1) || (b.1 <= y && y <= a.1) {
            let x = if (b.1 - a.1).abs() < 1e-12 {
                lo = lo.min(a.0.min(b.0));
                a.0.max(b.0)
            } else {
                a.0 + (y - a.1) * (b.0 - a.0) / (b.1 - a.1)
            };
            lo = lo.min(x);
            hi = hi.max(x);
        }
    }
    (lo <= hi).then_some((lo, hi))
}

/// Twice the signed area of `(a, b, c)`.
#[inline]
fn edge(a: (f64, f64), b: (f64, f64), c: (f64, f64)) -> f64 {
    (b.0 - a.0) * (c.1 - a.1) - (b.1 - a.1) * (c.0 - a.0)
}

/// Flat Lambertian + ambient colour of face `f`, whose centroid is at `centroid` in the camera
/// frame. The normal is turned towards the camera, so the inside of an open mesh shades too.
fn shade(
    mesh: &Mesh,
    f: usize,
    rot: &Matrix3<f64>,
    centroid: &Vector3<f64>,
    options: &RenderOptions,
) -> [u8; 3] {
    let mut normal = rot * mesh.face_normal(f).cast::<f64>();
    if normal.dot(centroid) > 0.0 {
        normal = -normal;
    }
    let lambert = normal.dot(&options.light).max(0.0);
    let intensity = options.ambient + (1.0 - options.ambient) * lambert;
    mesh.face_color(f, options.default_color)
        .map(|c| (c as f64 * intensity).round().clamp(0.0, 255.0) as u8)
}

#[cfg(test)]
mod tests {
    use super::{ceil_within, floor_at_zero};

    #[test]
    fn the_casts_round_as_floor_and_ceil_clamped() {
        let mut values = vec![
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            -0.0,
            1e300,
            -1e300,
        ];
        for i in -4000..4000 {
            let x = i as f64 / 64.0;
            values.extend([x, x + 1e-9, x - 1e-9]);
        }
        for x in values {
            let floor = x.floor().max(0.0) as usize;
            let ceil = (x.ceil() as i64).clamp(0, 40) as usize;
            assert_eq!(floor_at_zero(x), floor, "floor of {x}");
            assert_eq!(ceil_within(x, 40), ceil, "ceil of {x}");
        }
    }
}
