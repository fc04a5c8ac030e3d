//! Symmetry discovered from an SDF (`experts::symmetry`): the SYMSOL shapes, prisms and pyramids
//! whose groups are known, a part with no symmetry, and a nearly symmetric one. The SDF is the
//! mesh's exact one, baked as the SDF expert is (a trained expert adds its own error, which the
//! identity's residual absorbs).

use alignist::cad::{Mesh, Shape};
use alignist::experts::symmetry::{DiscoveredSymmetry, DiscoveryConfig, mesh_symmetry};
use nalgebra::Vector3;

/// The symmetry of `mesh` (mapped to NOCS about its surface centroid) from its baked exact SDF.
fn discover(mesh: &Mesh) -> DiscoveredSymmetry {
    let (nocs, _) = mesh.normalised_by(mesh.centroid_normalisation());
    mesh_symmetry(&nocs, &DiscoveryConfig::default()).expect("a closed mesh")
}

/// A closed solid over a regular `n`-gon of radius 1 in z = 0, scaled by `stretch` in x and y:
/// with `top` a copy of the base at that height (a prism, `Dn`), or else an apex there (a
/// pyramid, `Cn`). `apex_shift` moves the apex in x (breaking the symmetry).
fn solid(n: usize, stretch: [f32; 2], top: Option<f32>, apex: (f32, f32)) -> Mesh {
    let ring = |z: f32| -> Vec<Vector3<f32>> {
        (0..n)
            .map(|k| {
                let a = 2.0 * std::f32::consts::PI * k as f32 / n as f32;
                Vector3::new(stretch[0] * a.cos(), stretch[1] * a.sin(), z)
            })
            .collect()
    };
    let mut vertices = ring(0.0);
    vertices.push(Vector3::zeros()); // the base's centre: n
    let mut triangles = Vec::new();
    let n32 = n as u32;
    for k in 0..n32 {
        triangles.push([n32, (k + 1) % n32, k]); // the base, facing −z
    }
    match top {
        Some(h) => {
            vertices.extend(ring(h));
            vertices.push(Vector3::new(0.0, 0.0, h)); // the top's centre: 2n + 1
            let (t0, tc) = (n32 + 1, 2 * n32 + 1);
            for k in 0..n32 {
                let k1 = (k + 1) % n32;
                triangles.push([tc, t0 + k, t0 + k1]);
                triangles.push([k, k1, t0 + k1]);
                triangles.push([k, t0 + k1, t0 + k]);
            }
        }
        None => {
            vertices.push(Vector3::new(apex.1, 0.0, apex.0)); // n + 1
            for k in 0..n32 {
                triangles.push([k, (k + 1) % n32, n32 + 1]);
            }
        }
    }
    Mesh {
        source: format!("test:solid{n}"),
        vertices,
        triangles,
        colors: None,
    }
}

fn check(mesh: &Mesh, label: &str) -> DiscoveredSymmetry {
    let found = discover(mesh);
    eprintln!(
        "{}: {} (confidence {:.2}, {} rotations, baseline {:.4}, near {:?})",
        mesh.source, found.label, found.confidence, found.rotations, found.baseline, found.near
    );
    assert_eq!(found.label, label, "{}: {found:?}", mesh.source);
    found
}

#[test]
fn the_symsol_shapes_are_named_by_their_groups() {
    for (shape, label) in [
        (Shape::Tetrahedron, "T"),
        (Shape::Cube, "O"),
        (Shape::Icosahedron, "I"),
        (Shape::Cone, "cone"),
        (Shape::Cylinder, "cylinder"),
    ] {
        let found = check(&shape.mesh(), label);
        assert!(found.confidence > 0.3, "{shape:?}: {found:?}");
        assert!(found.near.is_none(), "{shape:?}: {found:?}");
    }
}

#[test]
fn a_c5_pyramid_is_c5_about_its_axis_though_its_box_is_off_centre() {
    let pyramid = solid(5, [1.0, 1.0], None, (1.5, 0.0));
    let found = check(&pyramid, "C5");
    assert_eq!(found.rotations, 5);
    let axis = Vector3::from(found.axes[0]);
    assert!(axis.z.abs() > 0.999, "axis {axis:?}");
    // Its bounding box's centre is not on the axis: about it, the part is not symmetric.
    let (lo, hi) = pyramid.bounds();
    assert!(((lo + hi) / 2.0).x.abs() > 0.05);
}

#[test]
fn prisms_and_boxes_are_dihedral() {
    check(&solid(5, [1.0, 1.0], Some(0.8), (0.0, 0.0)), "D5");
    check(&solid(4, [1.0, 0.6], Some(0.3), (0.0, 0.0)), "D2");
}

#[test]
fn a_part_without_symmetry_is_none() {
    let found = check(&solid(5, [1.0, 1.0], None, (1.5, 0.45)), "none");
    assert_eq!(found.rotations, 1);
    assert!(found.axes.is_empty());
}

#[test]
fn a_nearly_square_pyramid_is_c2_and_says_it_is_nearly_c4() {
    let found = check(&solid(4, [1.0, 0.85], None, (1.2, 0.0)), "C2");
    let near = found.near.as_ref().expect("a near-symmetry");
    assert_eq!(near.label, "C4", "{found:?}");
    assert!(near.residual > found.config.tolerance);
}
