//! Projective TSDF integration: the truncated signed distance of voxel centres to the surfaces
//! seen in depth images, averaged over the views (unit weights). Every voxel is independent:
//! threads take fixed chunks of voxels and each voxel visits the views in order, so the result
//! does not depend on the thread count.

use rayon::prelude::*;

use crate::error::{check_finite, invalid, Result};
use crate::splat::cpu::global_pool;
use crate::splat::Camera;

/// A z-depth image seen by `camera` (camera-space z per pixel, row-major; 0 where nothing was
/// observed).
#[derive(Debug, Clone, Copy)]
pub struct DepthView<'a> {
    pub depth: &'a [f32],
    pub camera: Camera,
}

/// Per voxel: the mean truncated signed distance over the views that observed it (in units of
/// `trunc`, at most 1) and how many views did (0: unobserved, its distance 0).
#[derive(Debug, Clone, PartialEq)]
pub struct Tsdf {
    pub distance: Vec<f32>,
    pub weight: Vec<f32>,
}

/// Voxels per task: enough work to amortise scheduling, small enough to balance two threads.
const CHUNK: usize = 1 << 14;

/// Integrates every view into the voxels at `centres` (world coordinates). A view observes a
/// voxel when it lies in front of the camera (z > 1e-6), projects into the image (pixel
/// floor(u), floor(v)), that pixel has a positive depth d, and the voxel is less than `trunc`
/// behind it (d - z >= -trunc); the view then adds min((d - z) / trunc, 1).
pub fn tsdf_integrate(centres: &[[f32; 3]], views: &[DepthView], trunc: f32) -> Result<Tsdf> {
    if !(trunc.is_finite() && trunc > 0.0) {
        return Err(invalid(format!(
            "tsdf: trunc must be positive, got {trunc}"
        )));
    }
    check_finite("tsdf centres", centres.as_flattened())?;
    for (i, view) in views.iter().enumerate() {
        view.camera.validate()?;
        if view.depth.len() != view.camera.pixels() {
            return Err(invalid(format!(
                "tsdf: depth image {i} holds {} values for a {}x{} camera",
                view.depth.len(),
                view.camera.width,
                view.camera.height
            )));
        }
        check_finite("tsdf depth", view.depth)?;
    }
    let mut distance = vec![0.0f32; centres.len()];
    let mut weight = vec![0.0f32; centres.len()];
    global_pool()?.install(|| {
        distance
            .par_chunks_mut(CHUNK)
            .zip(weight.par_chunks_mut(CHUNK))
            .zip(centres.par_chunks(CHUNK))
            .for_each(|((distance, weight), centres)| {
                for ((d, w), c) in distance.iter_mut().zip(weight).zip(centres) {
                    (*d, *w) = integrate_voxel(c, views, trunc);
                }
            });
    });
    Ok(Tsdf { distance, weight })
}

/// (mean truncated distance, views that observed it) of one voxel centre.
fn integrate_voxel(centre: &[f32; 3], views: &[DepthView], trunc: f32) -> (f32, f32) {
    let (mut sum, mut count) = (0.0f32, 0.0f32);
    for view in views {
        if let Some(sdf) = observed_distance(centre, view, trunc) {
            // Unit weights: the mean over the observing views, divided once at the end.
            count += 1.0;
            sum += (sdf / trunc).min(1.0);
        }
    }
    if count > 0.0 {
        (sum / count, count)
    } else {
        (0.0, 0.0)
    }
}

/// The signed distance d - z from the voxel to the surface `view` saw along its ray, where the
/// view observed the voxel (see [`tsdf_integrate`]).
#[inline]
fn observed_distance(centre: &[f32; 3], view: &DepthView, trunc: f32) -> Option<f32> {
    let cam = &view.camera;
    let m = &cam.world_to_cam;
    let p: [f32; 3] = std::array::from_fn(|r| {
        m[r][0] * centre[0] + m[r][1] * centre[1] + m[r][2] * centre[2] + m[r][3]
    });
    let z = p[2];
    if z <= 1e-6 {
        return None;
    }
    let u = cam.fx * p[0] / z + cam.cx;
    let v = cam.fy * p[1] / z + cam.cy;
    // Negated compares so that a NaN projection is outside.
    if !(u >= 0.0 && u < cam.width as f32 && v >= 0.0 && v < cam.height as f32) {
        return None;
    }
    // The clamps only matter where an f32 just below the size rounds up to it (huge images).
    let pixel = (v as usize).min(cam.height as usize - 1) * cam.width as usize
        + (u as usize).min(cam.width as usize - 1);
    let depth = view.depth[pixel];
    let sdf = depth - z;
    (depth > 0.0 && sdf >= -trunc).then_some(sdf)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splat::tests::origin_camera as camera;

    #[test]
    fn a_wall_gives_its_truncated_distance_in_front_and_nothing_far_behind() {
        // Every pixel sees a wall at z = 2.
        let cam = camera(8, 6);
        let depth = vec![2.0f32; cam.pixels()];
        let view = DepthView {
            depth: &depth,
            camera: cam,
        };
        let trunc = 0.1;
        let centres = [
            [0.0, 0.0, 1.95],  // 0.05 in front: 0.5
            [0.0, 0.0, 1.0],   // far in front: clamped to 1
            [0.0, 0.0, 2.05],  // 0.05 behind: -0.5
            [0.0, 0.0, 2.5],   // beyond the band behind: unobserved
            [0.0, 0.0, -1.0],  // behind the camera: unobserved
            [50.0, 0.0, 1.95], // outside the image: unobserved
        ];
        let out = tsdf_integrate(&centres, &[view, view], trunc).unwrap();
        let want = [0.5, 1.0, -0.5, 0.0, 0.0, 0.0];
        for (got, want) in out.distance.iter().zip(want) {
            assert!((got - want).abs() < 1e-5, "{got} vs {want}");
        }
        assert_eq!(out.weight, vec![2.0, 2.0, 2.0, 0.0, 0.0, 0.0]);
    }

    #[test]
    fn unobserved_pixels_and_bad_inputs() {
        let cam = camera(4, 4);
        let depth = vec![0.0f32; cam.pixels()]; // nothing observed
        let view = DepthView {
            depth: &depth,
            camera: cam,
        };
        let out = tsdf_integrate(&[[0.0, 0.0, 1.0]], &[view], 0.1).unwrap();
        assert_eq!((out.distance[0], out.weight[0]), (0.0, 0.0));
        assert!(tsdf_integrate(&[[0.0, 0.0, 1.0]], &[view], 0.0).is_err());
        assert!(tsdf_integrate(&[[f32::NAN, 0.0, 1.0]], &[view], 0.1).is_err());
        let short = [1.0f32; 3];
        let bad = DepthView {
            depth: &short,
            camera: cam,
        };
        assert!(tsdf_integrate(&[[0.0, 0.0, 1.0]], &[bad], 0.1).is_err());
    }
}
