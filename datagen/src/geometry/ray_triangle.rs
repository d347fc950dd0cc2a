//! The render's ray test: which surface a ray through a novel pixel centre meets first. Watertight
//! ray/triangle intersection after Woop, Benthin and Wald, "Watertight Ray/Triangle Intersection"
//! (JCGT 2013), in f64, with closed triangles, plus the mesh's vertices as points of its surface.
//!
//! Why not the f32 Möller–Trumbore test that the co-visibility segments use: its barycentric
//! coordinates are rounded separately per triangle (and it refuses −0.0), so a ray through a
//! shared edge or vertex can miss both triangles. At the source pose every pixel ray passes
//! through its own pixel's mesh vertex, and a quarter of the pixels came out as holes.
//!
//! Here each ray is sheared onto the +z axis once; a triangle's corners are mapped by the same
//! arithmetic wherever they appear, and the edge function of an edge is evaluated from its two
//! corners alone, so the two triangles on an edge see exactly opposite values: any ray meets at
//! least one of them (watertight). Edges and corners belong to the triangle (closed: a zero edge
//! function counts as inside), so the mesh's border is part of it, and a pixel centre on a shared
//! edge is claimed by both triangles at the same surface point.
//!
//! A ray passing within [`VERTEX_TOLERANCE`] (an angle) of a mesh vertex hits that vertex: the
//! vertices are the depth map's samples, which belong to the surface even where no triangle joins
//! them (an isolated valid pixel, a one-pixel-wide image) and where rounding leaves the ray through
//! a border vertex a hair outside its triangles (the last row and column at the source pose).

use glam::DVec3;

/// Angle (radians) within which a ray passing a vertex hits it: 10⁶ × the f64 round-off of a point
/// lifted from a pixel and projected back (~1e-15), and far below a pixel's angle (1e-9 rad is a
/// millionth of a pixel at a focal length of 1000 px), so it decides only rays aimed at a vertex.
pub const VERTEX_TOLERANCE: f64 = 1e-9;

/// A ray with the shear that maps it onto +z (Woop et al., section 3).
#[derive(Debug, Clone, Copy)]
pub struct RenderRay {
    origin: DVec3,
    direction: DVec3,
    /// The axes that become x, y and z: z is the direction's largest component, x and y the next
    /// two in turn (swapped when the z component is negative, keeping the winding).
    axes: [usize; 3],
    /// (direction[x] / direction[z], direction[y] / direction[z], 1 / direction[z]).
    shear: DVec3,
}

impl RenderRay {
    /// The ray from `origin` along `direction` (unit length: hit distances are along it).
    pub fn new(origin: DVec3, direction: DVec3) -> Self {
        let magnitude = direction.abs();
        let z = if magnitude.x >= magnitude.y && magnitude.x >= magnitude.z {
            0
        } else if magnitude.y >= magnitude.z {
            1
        } else {
            2
        };
        let (mut x, mut y) = ((z + 1) % 3, (z + 2) % 3);
        if direction[z] < 0.0 {
            std::mem::swap(&mut x, &mut y);
        }
        let shear = DVec3::new(direction[x] / direction[z], direction[y] / direction[z], 1.0 / direction[z]);
        Self { origin, direction, axes: [x, y, z], shear }
    }

    /// The ray's origin.
    pub fn origin(&self) -> DVec3 {
        self.origin
    }

    /// The ray's direction.
    pub fn direction(&self) -> DVec3 {
        self.direction
    }

    /// A corner in ray space: sheared (x, y) relative to the ray, and z scaled.
    fn sheared(&self, corner: DVec3) -> DVec3 {
        let [x, y, z] = self.axes;
        let p = corner - self.origin;
        DVec3::new(p[x] - self.shear.x * p[z], p[y] - self.shear.y * p[z], self.shear.z * p[z])
    }

    /// Distance along the ray at which it meets the closed triangle `corners`, if it does in front
    /// of the origin; None for a miss or a triangle seen edge-on.
    pub fn triangle_hit(&self, corners: [DVec3; 3]) -> Option<f64> {
        let [a, b, c] = corners.map(|corner| self.sheared(corner));
        // The edge function of edge (p, q) is p.x q.y − p.y q.x: swapping p and q negates it
        // exactly, so a shared edge gives its two triangles opposite values.
        let edge = |p: DVec3, q: DVec3| p.x * q.y - p.y * q.x;
        let (u, v, w) = (edge(b, c), edge(c, a), edge(a, b));
        if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
            return None;
        }
        let determinant = u + v + w;
        if determinant == 0.0 {
            return None;
        }
        let t = (u * a.z + v * b.z + w * c.z) / determinant;
        (t > 0.0).then_some(t)
    }

    /// Distance along the ray to `point`, if the ray passes it within [`VERTEX_TOLERANCE`] in
    /// front of the origin.
    pub fn vertex_hit(&self, point: DVec3) -> Option<f64> {
        let offset = point - self.origin;
        let along = offset.dot(self.direction);
        (along > 0.0 && offset.cross(self.direction).length() <= VERTEX_TOLERANCE * along).then_some(along)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ray(origin: [f64; 3], direction: [f64; 3]) -> RenderRay {
        RenderRay::new(DVec3::from(origin), DVec3::from(direction).normalize())
    }

    #[test]
    fn a_ray_through_a_triangle_hits_it_at_its_distance_from_either_side() {
        let corners = [DVec3::new(-1.0, -1.0, 5.0), DVec3::new(1.0, -1.0, 5.0), DVec3::new(0.0, 1.0, 5.0)];
        let flipped = [corners[0], corners[2], corners[1]];
        for direction in [[0.0, 0.0, 1.0], [0.05, -0.05, 1.0]] {
            let r = ray([0.0; 3], direction);
            let expected = 5.0 / r.direction().z;
            for triangle in [corners, flipped] {
                let t = r.triangle_hit(triangle).expect("hit");
                assert!((t - expected).abs() < 1e-12, "{t} vs {expected}");
            }
        }
        assert_eq!(ray([0.0; 3], [0.0, 0.0, -1.0]).triangle_hit(corners), None, "behind the origin");
        assert_eq!(ray([0.0; 3], [0.5, 0.0, 1.0]).triangle_hit(corners), None, "beside it");
        // Seen edge-on: no hit.
        let edge_on = [DVec3::new(0.0, -1.0, 4.0), DVec3::new(0.0, 1.0, 4.0), DVec3::new(0.0, 0.0, 6.0)];
        assert_eq!(ray([0.0; 3], [0.0, 0.0, 1.0]).triangle_hit(edge_on), None);
    }

    #[test]
    fn rays_through_shared_edges_and_vertices_hit_a_triangle_of_a_fan() {
        // A fan of triangles around (0, 0, 4) whose shared edges lie on awkward f64 values: every
        // ray aimed at an edge, at the centre or at random points of the fan hits some triangle.
        let centre = DVec3::new(0.1, 0.3, 4.0);
        let rim: Vec<DVec3> = (0..7)
            .map(|k| {
                let angle = f64::from(k) * std::f64::consts::TAU / 7.0 + 0.3;
                centre + DVec3::new(angle.cos(), angle.sin(), 0.2 * angle.sin())
            })
            .collect();
        let triangles: Vec<[DVec3; 3]> = (0..7).map(|k| [centre, rim[k], rim[(k + 1) % 7]]).collect();
        let origins = [DVec3::ZERO, DVec3::new(0.3, -0.2, 0.1), DVec3::new(-2.0, 1.0, -1.0)];
        for origin in origins {
            let mut targets = vec![centre];
            for corner in &rim {
                targets.extend((1..50).map(|s| centre + (*corner - centre) * (f64::from(s) / 50.0)));
            }
            for target in targets {
                let r = RenderRay::new(origin, (target - origin).normalize());
                assert!(triangles.iter().any(|&t| r.triangle_hit(t).is_some()), "{origin} → {target}");
            }
        }
    }

    #[test]
    fn a_ray_aimed_at_a_point_hits_it_and_a_ray_beside_it_does_not() {
        let point = DVec3::new(0.3, -0.7, 6.1);
        let r = RenderRay::new(DVec3::ZERO, point.normalize());
        let t = r.vertex_hit(point).expect("hit");
        assert!((t - point.length()).abs() < 1e-12);
        let beside = RenderRay::new(DVec3::ZERO, (point + DVec3::new(1e-6, 0.0, 0.0)).normalize());
        assert_eq!(beside.vertex_hit(point), None);
        let away = RenderRay::new(DVec3::ZERO, -point.normalize());
        assert_eq!(away.vertex_hit(point), None);
    }
}
