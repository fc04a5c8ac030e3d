//! Scenes as a camera sees them: several meshes in one z-buffer, each with a material (base
//! colour or the mesh's own colours, roughness, metalness), shaded per pixel from normals
//! interpolated over smooth parts of the surface (hard edges kept), under coloured directional
//! lights plus an ambient term. Colours are linear (not yet exposed or gamma-encoded: a camera
//! model does that, in `src/data/realism.rs`).
//!
//! Shading is Blinn–Phong with a roughness-derived exponent and Schlick's Fresnel, energy
//! normalised (`(n + 8) / 8π`): the usual real-time stand-in for a microfacet model. Object 0 of a
//! scene is the subject: its mask, depth and NOCS come back as a [`Render`], with the number of
//! pixels it would cover without the others in front ([`SceneRender::visible_fraction`]).

use nalgebra::{Matrix3, Vector3};

use super::render::{NEAR, Raster};
use super::{Camera, Mesh, MeshColors, Pose, Render};

/// Surface parameters of one object.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Material {
    /// Base colour, linear RGB in `[0, 1]` (multiplied by the mesh's own colours when it has any).
    pub base: [f32; 3],
    /// Perceptual roughness in `(0, 1]`: 1 is matte, small values give tight highlights.
    pub roughness: f32,
    /// Metalness in `[0, 1]`: metals have no diffuse term and tinted highlights.
    pub metalness: f32,
}

impl Material {
    /// A matte white material (the mesh's own colours show as they are).
    pub const MATTE: Material = Material {
        base: [1.0, 1.0, 1.0],
        roughness: 1.0,
        metalness: 0.0,
    };
}

/// A directional light.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Light {
    /// Unit direction towards the light, in the camera frame.
    pub direction: Vector3<f64>,
    /// Linear RGB radiance (colour × intensity).
    pub radiance: [f32; 3],
}

/// The lights of a scene.
#[derive(Debug, Clone, PartialEq)]
pub struct Lighting {
    /// Directional lights.
    pub lights: Vec<Light>,
    /// Ambient linear RGB radiance.
    pub ambient: [f32; 3],
}

/// Per-corner normals of a mesh in its own frame, by smoothing groups: around each vertex, faces
/// that share an edge whose dihedral angle is under `crease` form one group, and a corner's normal
/// is the area-weighted mean of its group's face normals. Curved surfaces shade smoothly (both
/// sides of a smooth edge get the same normal at its ends) and edges sharper than `crease` stay
/// hard.
///
/// Made once per mesh, it also records whether the mesh is closed and wound outwards (its back
/// faces are then always hidden behind its front faces, and the renderer skips them).
#[derive(Debug, Clone, PartialEq)]
pub struct CornerNormals {
    /// Per face, the normals at its three corners.
    corners: Vec<[Vector3<f32>; 3]>,
    /// Closed and wound outwards: see [`CornerNormals::closed_outward`].
    closed_outward: bool,
}

impl CornerNormals {
    /// Corner normals with a crease angle of `crease_deg` degrees.
    pub fn new(mesh: &Mesh, crease_deg: f32) -> CornerNormals {
        // Vertices are identified by position, so a file that repeats them per face still shades
        // smoothly where it is smooth.
        let mut id_of = std::collections::HashMap::new();
        let ids: Vec<usize> = mesh
            .vertices
            .iter()
            .map(|v| {
                let n = id_of.len();
                *id_of
                    .entry([v.x.to_bits(), v.y.to_bits(), v.z.to_bits()])
                    .or_insert(n)
            })
            .collect();
        let corner_ids: Vec<[usize; 3]> = mesh
            .triangles
            .iter()
            .map(|t| t.map(|i| ids[i as usize]))
            .collect();
        let face_normal: Vec<Vector3<f32>> = (0..mesh.triangles.len())
            .map(|f| mesh.face_normal(f))
            .collect();
        let mut around: Vec<Vec<usize>> = vec![Vec::new(); id_of.len()];
        for (f, t) in corner_ids.iter().enumerate() {
            for &v in t {
                around[v].push(f);
            }
        }
        let cos_crease = crease_deg.to_radians().cos();
        let mut corners: Vec<[Vector3<f32>; 3]> = face_normal.iter().map(|n| [*n; 3]).collect();
        for (v, fan) in around.iter().enumerate() {
            // Union–find over the fan: faces joined through smooth shared edges.
            let mut group: Vec<usize> = (0..fan.len()).collect();
            fn root(group: &mut [usize], mut i: usize) -> usize {
                while group[i] != i {
                    group[i] = group[group[i]];
                    i = group[i];
                }
                i
            }
            for a in 0..fan.len() {
                for b in a + 1..fan.len() {
                    let (fa, fb) = (fan[a], fan[b]);
                    let shares_edge = corner_ids[fa]
                        .iter()
                        .any(|&u| u != v && corner_ids[fb].contains(&u));
                    if shares_edge && face_normal[fa].dot(&face_normal[fb]) >= cos_crease {
                        let (ra, rb) = (root(&mut group, a), root(&mut group, b));
                        group[ra] = rb;
                    }
                }
            }
            let mut sums = vec![Vector3::<f32>::zeros(); fan.len()];
            for (a, &f) in fan.iter().enumerate() {
                let r = root(&mut group, a);
                sums[r] += face_normal[f] * mesh.face_area(f);
            }
            for (a, &f) in fan.iter().enumerate() {
                let r = root(&mut group, a);
                let n = sums[r].try_normalize(0.0).unwrap_or(face_normal[f]);
                let k = corner_ids[f].iter().position(|&u| u == v).unwrap_or(0);
                corners[f][k] = n;
            }
        }
        let closed_outward = {
            let welded = mesh.welded();
            welded.check_closed().is_ok() && welded.signed_volume() > 0.0
        };
        CornerNormals {
            corners,
            closed_outward,
        }
    }

    /// Whether the mesh is closed, consistently wound and wound counter-clockwise seen from
    /// outside (positive volume): seen from outside, its back faces are hidden.
    pub fn closed_outward(&self) -> bool {
        self.closed_outward
    }

    /// The normals at the three corners of face `f`.
    pub fn of(&self, f: usize) -> [Vector3<f32>; 3] {
        self.corners[f]
    }
}

/// One object of a scene.
#[derive(Debug, Clone, Copy)]
pub struct SceneObject<'a> {
    /// The mesh.
    pub mesh: &'a Mesh,
    /// Its corner normals ([`CornerNormals::new`] of `mesh`).
    pub normals: &'a CornerNormals,
    /// Its pose in the camera.
    pub pose: Pose,
    /// Its material.
    pub material: Material,
}

/// A rendered scene.
pub struct SceneRender {
    /// Linear RGB per pixel; `None` where no object is seen (the background shows).
    pub linear: Vec<Option<[f32; 3]>>,
    /// Object 0 as [`crate::cad::render`] gives it (mask, depth, NOCS of its visible pixels);
    /// its `rgb` is black: the colour is in `linear`.
    pub subject: Render,
    /// Pixels object 0 covers with nothing in front of it.
    pub unoccluded_pixels: usize,
}

impl SceneRender {
    /// The fraction of object 0's pixels that no other object hides (1 with no occluder; 0 when
    /// it is not in view at all).
    pub fn visible_fraction(&self) -> f64 {
        if self.unoccluded_pixels == 0 {
            0.0
        } else {
            self.subject.mask_area() as f64 / self.unoccluded_pixels as f64
        }
    }
}

/// Renders `objects` (object 0 first: the subject) through `camera` under `lighting`.
pub fn render_scene(
    objects: &[SceneObject<'_>],
    camera: &Camera,
    lighting: &Lighting,
) -> SceneRender {
    SceneRaster::of(objects, camera).shade(camera, lighting)
}

/// A scene's geometry drawn into the z-buffer, not yet shaded: objects can be added on top (an
/// occluder tried at a few places) before the one shading pass. Its shading gives what
/// [`render_scene`] of the same objects in the same order gives.
#[derive(Clone)]
pub struct SceneRaster<'a> {
    raster: Raster,
    /// The objects drawn, in order.
    objects: Vec<SceneObject<'a>>,
    /// Pixels object 0 covered before any other object was drawn.
    unoccluded_pixels: usize,
}

impl<'a> SceneRaster<'a> {
    /// `objects` drawn, in order.
    pub fn of(objects: &[SceneObject<'a>], camera: &Camera) -> SceneRaster<'a> {
        let mut scene = SceneRaster {
            raster: Raster::new(camera.width as usize, camera.height as usize),
            objects: Vec::with_capacity(objects.len() + 1),
            unoccluded_pixels: 0,
        };
        for o in objects {
            scene.draw(*o, camera);
        }
        scene
    }

    /// Draws `o` as the next object.
    pub fn draw(&mut self, o: SceneObject<'a>, camera: &Camera) {
        let index = self.objects.len();
        let rotation = *o.pose.rotation.matrix();
        let cam: Vec<Vector3<f64>> = o
            .mesh
            .vertices
            .iter()
            .map(|v| rotation * v.cast::<f64>() + o.pose.translation)
            .collect();
        let screen: Vec<(f64, f64)> = cam.iter().map(|p| camera.project(p)).collect();
        // A closed mesh wholly in front of the camera is seen from outside: its back faces
        // are hidden behind its front faces, so they are not drawn.
        let cull = o.normals.closed_outward() && cam.iter().all(|p| p.z > NEAR);
        self.raster
            .draw_mesh(o.mesh, index as u16, &cam, &screen, cull);
        if index == 0 {
            self.unoccluded_pixels = self.subject_pixels();
        }
        self.objects.push(o);
    }

    /// [`SceneRender::visible_fraction`] of the objects drawn so far.
    pub fn visible_fraction(&self) -> f64 {
        if self.unoccluded_pixels == 0 {
            return 0.0;
        }
        self.subject_pixels() as f64 / self.unoccluded_pixels as f64
    }

    /// Pixels where object 0 is the nearest.
    fn subject_pixels(&self) -> usize {
        self.raster.object_at.iter().filter(|&&o| o == 0).count()
    }

    /// The shaded render of the objects drawn.
    pub fn shade(self, camera: &Camera, lighting: &Lighting) -> SceneRender {
        let SceneRaster {
            raster,
            objects,
            unoccluded_pixels,
        } = self;
        let (w, h) = (camera.width as usize, camera.height as usize);
        let rotations: Vec<Matrix3<f64>> =
            objects.iter().map(|o| *o.pose.rotation.matrix()).collect();
        let mut linear = Vec::with_capacity(w * h);
        let mut mask = Vec::with_capacity(w * h);
        let mut depth = Vec::with_capacity(w * h);
        let mut nocs = Vec::with_capacity(w * h);
        for idx in 0..w * h {
            let object = raster.object_at[idx];
            if object == u16::MAX {
                linear.push(None);
            } else {
                let o = &objects[object as usize];
                let (x, y) = ((idx % w) as f64 + 0.5, (idx / w) as f64 + 0.5);
                let z = raster.zbuf[idx];
                let point = Vector3::new(
                    (x - camera.cx) / camera.fx * z,
                    (y - camera.cy) / camera.fy * z,
                    z,
                );
                linear.push(Some(shade_pixel(
                    o,
                    &rotations[object as usize],
                    raster.face_at[idx] as usize,
                    raster.bary[idx],
                    &point,
                    lighting,
                )));
            }
            let subject = object == 0;
            mask.push(subject);
            depth.push(if subject {
                raster.zbuf[idx] as f32
            } else {
                0.0
            });
            nocs.push(if subject {
                raster.nocs[idx]
            } else {
                [f32::NAN; 3]
            });
        }
        SceneRender {
            linear,
            subject: Render {
                width: camera.width,
                height: camera.height,
                rgb: vec![0; w * h * 3],
                mask,
                depth,
                nocs,
            },
            unoccluded_pixels,
        }
    }
}

/// The albedo of the point with barycentric weights `bary` on face `f` of `mesh`: the material's
/// base colour times the mesh's own colour there (vertex colours interpolated), linear RGB.
fn albedo(mesh: &Mesh, f: usize, bary: [f32; 3], base: [f32; 3]) -> [f32; 3] {
    let own = match &mesh.colors {
        None => return base,
        Some(MeshColors::PerFace(c)) => c[f].map(srgb_to_linear),
        Some(MeshColors::PerVertex(c)) => {
            let t = mesh.triangles[f];
            std::array::from_fn(|k| {
                (0..3)
                    .map(|j| bary[j] * srgb_to_linear(c[t[j] as usize][k]))
                    .sum()
            })
        }
        Some(MeshColors::Texture(tex)) => {
            let t = mesh.triangles[f];
            let uv =
                std::array::from_fn(|k| (0..3).map(|j| bary[j] * tex.uv[t[j] as usize][k]).sum());
            tex.sample(uv)
                .map(|c| srgb_to_linear(c.round().clamp(0.0, 255.0) as u8))
        }
    };
    std::array::from_fn(|k| own[k] * base[k])
}

/// sRGB byte to linear `[0, 1]`, from a table of the 256 values made on first use (textures and
/// photographs call it per texel, four texels a bilinear lookup).
pub fn srgb_to_linear(c: u8) -> f32 {
    static TABLE: std::sync::OnceLock<[f32; 256]> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| std::array::from_fn(|c| srgb_formula(c as u8)))[c as usize]
}

/// The sRGB transfer function's inverse on one byte.
fn srgb_formula(c: u8) -> f32 {
    let c = c as f32 / 255.0;
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Blinn–Phong with Schlick's Fresnel at `point` (camera frame) of face `f` of `object`.
fn shade_pixel(
    object: &SceneObject<'_>,
    rotation: &Matrix3<f64>,
    f: usize,
    bary: [f32; 3],
    point: &Vector3<f64>,
    lighting: &Lighting,
) -> [f32; 3] {
    let corners = &object.normals.corners[f];
    let n_obj: Vector3<f32> = corners[0] * bary[0] + corners[1] * bary[1] + corners[2] * bary[2];
    let geometric = rotation * object.mesh.face_normal(f).cast::<f64>();
    let mut normal = (rotation * n_obj.cast::<f64>())
        .try_normalize(0.0)
        .unwrap_or(geometric);
    let view = -point.normalize();
    if geometric.dot(&view) < 0.0 {
        // A face seen from behind (the inside of an open mesh): its shading normal turns too.
        normal = -normal;
    }
    let m = &object.material;
    let albedo = albedo(object.mesh, f, bary, m.base);
    let alpha = (m.roughness * m.roughness).clamp(1e-3, 1.0);
    let exponent = (2.0 / (alpha * alpha) - 2.0).clamp(1.0, 4096.0);
    let norm = (exponent + 8.0) / (8.0 * std::f32::consts::PI);
    let f0: [f32; 3] =
        std::array::from_fn(|k| 0.04 * (1.0 - m.metalness) + albedo[k] * m.metalness);
    let mut out: [f32; 3] =
        std::array::from_fn(|k| lighting.ambient[k] * albedo[k] * (1.0 - 0.5 * m.metalness));
    for light in &lighting.lights {
        let n_dot_l = normal.dot(&light.direction) as f32;
        if n_dot_l <= 0.0 {
            continue;
        }
        let half = (light.direction + view).normalize();
        let n_dot_h = normal.dot(&half).max(0.0) as f32;
        let v_dot_h = view.dot(&half).max(0.0) as f32;
        let spec = norm * n_dot_h.powf(exponent) * n_dot_l;
        let schlick = (1.0 - v_dot_h).powi(5);
        for k in 0..3 {
            let fresnel = f0[k] + (1.0 - f0[k]) * schlick;
            let diffuse = albedo[k] * (1.0 - m.metalness) * n_dot_l;
            out[k] += light.radiance[k] * (diffuse + fresnel * spec);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cad::shapes::{ALL_SHAPES, uv_sphere_mesh};
    use nalgebra::{Rotation3, Vector3};
    use rand::{RngExt, SeedableRng};

    /// The raster of `mesh` at `pose` through a 96 px camera, back faces culled or not.
    fn raster(mesh: &Mesh, pose: &Pose, cull: bool) -> Raster {
        let camera = Camera::square(96);
        let cam: Vec<Vector3<f64>> = mesh
            .vertices
            .iter()
            .map(|v| pose.rotation * v.cast::<f64>() + pose.translation)
            .collect();
        let screen: Vec<(f64, f64)> = cam.iter().map(|p| camera.project(p)).collect();
        let mut r = Raster::new(96, 96);
        r.draw_mesh(mesh, 0, &cam, &screen, cull);
        r
    }

    #[test]
    fn closed_outward_meshes_are_recognised() {
        let mut meshes: Vec<Mesh> = ALL_SHAPES.iter().map(|s| s.mesh()).collect();
        meshes.push(uv_sphere_mesh(16, 8));
        for m in &meshes {
            assert!(CornerNormals::new(m, 35.0).closed_outward(), "{}", m.source);
            // Wound inwards, or with a face missing: not.
            let mut inward = m.clone();
            inward.triangles.iter_mut().for_each(|t| t.swap(1, 2));
            assert!(!CornerNormals::new(&inward, 35.0).closed_outward());
            let mut open = m.clone();
            open.triangles.pop();
            assert!(!CornerNormals::new(&open, 35.0).closed_outward());
        }
    }

    /// Culling the back faces of a closed mesh seen from outside changes no pixel: the same
    /// depth, face and weights everywhere, at random poses (near enough to fill the frame and
    /// to be cut by its edge).
    #[test]
    fn culling_back_faces_of_closed_meshes_changes_no_pixel() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let mut meshes: Vec<Mesh> = ALL_SHAPES.iter().map(|s| s.mesh()).collect();
        meshes.push(uv_sphere_mesh(16, 8));
        let mut covered = 0;
        for m in &meshes {
            for _ in 0..20 {
                let pose = Pose {
                    rotation: Rotation3::new(Vector3::new(
                        rng.random_range(-3.0..3.0),
                        rng.random_range(-3.0..3.0),
                        rng.random_range(-3.0..3.0),
                    )),
                    translation: Vector3::new(
                        rng.random_range(-0.5..0.5),
                        rng.random_range(-0.5..0.5),
                        rng.random_range(1.2..4.0),
                    ),
                };
                let (all, culled) = (raster(m, &pose, false), raster(m, &pose, true));
                assert_eq!(all.zbuf, culled.zbuf, "{}", m.source);
                assert_eq!(all.face_at, culled.face_at, "{}", m.source);
                assert_eq!(all.bary, culled.bary, "{}", m.source);
                covered += all.face_at.iter().filter(|&&f| f != u32::MAX).count();
            }
        }
        assert!(covered > 100_000, "the poses cover {covered} pixels");
    }
}
