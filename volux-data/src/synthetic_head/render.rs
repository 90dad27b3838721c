//! Rendering a synthetic head with the dataset camera: sphere tracing of the signed distance,
//! exact normals from its gradient, and the intrinsic layers (albedo, camera-space normals,
//! coverage mask, depth, per-pixel specular weights), optionally supersampled.

use rayon::prelude::*;
use volux_model::pose::Pose;
use volux_model::ray_sampling::{CameraConfig, camera_basis, camera_rays};

use super::head::{BOUNDING_RADIUS, Material, SyntheticHead};
use super::scalar::Dual;
use crate::relighting::IntrinsicImage;

/// Sphere tracing steps by this fraction of the distance bound (the ellipsoids and smooth blends
/// are bounds that can slightly overestimate near seams).
const STEP_FRACTION: f64 = 0.8;
/// A ray has hit the surface when the distance falls below this.
const HIT_EPSILON: f64 = 2e-5;
const MAX_STEPS: usize = 256;
/// Newton steps onto the surface after a hit.
const REFINE_STEPS: usize = 8;
/// The longest Newton step: the ray is already within [`HIT_EPSILON`] of the surface.
const MAX_REFINE_STEP: f64 = 1e-3;
/// Height of the outer iso-surface whose normal softens skin shading (see `photo`): the
/// distance field's level sets outside the head round off creases and small forms.
const SOFT_NORMAL_OFFSET: f64 = 0.02;

/// Image size and sampling of a render.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderSettings {
    pub width: usize,
    pub height: usize,
    /// Rays per pixel along each axis (1: one ray through the pixel centre; 2: a 2x2 grid,
    /// which anti-aliases the silhouette and the photo).
    pub supersample: usize,
    pub camera: CameraConfig,
}

impl RenderSettings {
    /// A square image of `side` pixels, one ray per pixel, the dataset camera.
    pub fn square(side: usize) -> RenderSettings {
        RenderSettings {
            width: side,
            height: side,
            supersample: 1,
            camera: CameraConfig::new(),
        }
    }
}

/// One ray's surface point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceHit {
    /// Distance along the (unit) ray.
    pub t: f64,
    /// World-space position.
    pub point: [f64; 3],
    /// Unit world-space normal: the normalised gradient of the signed distance.
    pub normal: [f64; 3],
    /// Unit world-space normal of the iso-surface `SOFT_NORMAL_OFFSET` outside, which follows
    /// the large forms and not the creases (for the photo's subsurface softening).
    pub soft_normal: [f64; 3],
    /// World-space ray direction.
    pub ray: [f64; 3],
    pub material: Material,
}

/// A head's intrinsic layers at one pose, and the surface points behind every pixel.
#[derive(Clone, Debug)]
pub struct HeadRender {
    /// Albedo (mean over the pixel's covered rays), unit camera-space normals, coverage mask
    /// and pose: what relighting needs.
    pub image: IntrinsicImage,
    /// Expected ray depth with the uncovered part at the camera's far bound (the generator's
    /// convention).
    pub depth: Vec<f32>,
    /// Specular weights of the lobes 1, 16, 32, 64 per pixel, pixel-major.
    pub specular_weights: Vec<f32>,
    /// The rays of each pixel that hit the head.
    pub hits: Vec<Vec<SurfaceHit>>,
    /// Rays per pixel.
    pub rays_per_pixel: usize,
    /// The camera the render was made with.
    pub camera: CameraConfig,
}

/// Distance along the ray `o + t d` to the surface within the camera's bounds, if any.
pub fn trace(head: &SyntheticHead, o: [f64; 3], d: [f64; 3], near: f64, far: f64) -> Option<f64> {
    // Only the bounding sphere can contain surface.
    let b = o[0] * d[0] + o[1] * d[1] + o[2] * d[2];
    let c = o[0] * o[0] + o[1] * o[1] + o[2] * o[2] - BOUNDING_RADIUS * BOUNDING_RADIUS;
    let disc = b * b - c;
    if disc <= 0.0 {
        return None;
    }
    let (t0, t1) = (near.max(-b - disc.sqrt()), far.min(-b + disc.sqrt()));
    let mut t = t0;
    let mut closest = f64::INFINITY;
    for _ in 0..MAX_STEPS {
        if t > t1 {
            return None;
        }
        let dist = head.distance(at(o, d, t));
        if dist < HIT_EPSILON {
            return Some(refine(head, o, d, t));
        }
        closest = closest.min(dist);
        t += STEP_FRACTION * dist;
    }
    // Out of steps (a grazing ray crawling along the surface): a hit if it is still close.
    (closest < 1e-3).then(|| refine(head, o, d, t))
}

/// Newton steps along the ray onto the surface (the exact gradient gives the slope), so that
/// the depth layer lies on the surface to far better than [`HIT_EPSILON`], grazing rays too.
fn refine(head: &SyntheticHead, o: [f64; 3], d: [f64; 3], mut t: f64) -> f64 {
    for _ in 0..REFINE_STEPS {
        let f = head.distance(Dual::point(at(o, d, t)));
        if f.v.abs() < 1e-12 {
            break;
        }
        let slope = f.d[0] * d[0] + f.d[1] * d[1] + f.d[2] * d[2];
        // Towards the surface along a ray that enters it (bounded, for rays that graze it); a
        // plain sphere-tracing step where the ray runs parallel to the surface.
        let step = if slope < -1e-3 { -f.v / slope } else { f.v };
        t += step.clamp(-MAX_REFINE_STEP, MAX_REFINE_STEP);
    }
    t
}

fn at(o: [f64; 3], d: [f64; 3], t: f64) -> [f64; 3] {
    std::array::from_fn(|k| o[k] + t * d[k])
}

fn unit(v: [f64; 3]) -> Option<[f64; 3]> {
    let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    (len > 1e-12 && len.is_finite()).then(|| v.map(|c| c / len))
}

/// The surface point of one ray, if it hits.
pub fn hit(
    head: &SyntheticHead,
    o: [f64; 3],
    d: [f64; 3],
    camera: &CameraConfig,
) -> Option<SurfaceHit> {
    let t = trace(head, o, d, camera.near, camera.far)?;
    let point = at(o, d, t);
    let normal = unit(head.gradient(point)).unwrap_or(d.map(|c| -c));
    let outside = std::array::from_fn(|k| point[k] + SOFT_NORMAL_OFFSET * normal[k]);
    let soft_normal = unit(head.gradient(outside)).unwrap_or(normal);
    Some(SurfaceHit {
        t,
        point,
        normal,
        soft_normal,
        ray: d,
        material: head.material(point),
    })
}

/// Renders `head` seen from `pose`: rows in parallel, deterministic for any number of
/// threads (every pixel is computed on its own).
pub fn render(head: &SyntheticHead, pose: Pose, settings: &RenderSettings) -> HeadRender {
    let (w, h, s) = (settings.width, settings.height, settings.supersample.max(1));
    let camera = &settings.camera;
    let (origins, dirs) = camera_rays(camera, pose, w * s, h * s);
    let [right, up, back] = camera_basis(camera, pose);
    let hits: Vec<Vec<SurfaceHit>> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let mut found = Vec::with_capacity(s * s);
            for sy in 0..s {
                for sx in 0..s {
                    let r = (y * s + sy) * w * s + x * s + sx;
                    if let Some(hit) = hit(head, origins[r], dirs[r], camera) {
                        found.push(hit);
                    }
                }
            }
            found
        })
        .collect();
    let rays = (s * s) as f64;
    let mut albedo = Vec::with_capacity(w * h);
    let mut normals = Vec::with_capacity(w * h);
    let mut mask = Vec::with_capacity(w * h);
    let mut depth = Vec::with_capacity(w * h);
    let mut specular_weights = Vec::with_capacity(4 * w * h);
    for found in &hits {
        let n = found.len() as f64;
        let coverage = n / rays;
        let mean = |f: &dyn Fn(&SurfaceHit) -> f64| {
            if found.is_empty() {
                0.0
            } else {
                found.iter().map(f).sum::<f64>() / n
            }
        };
        albedo.push(std::array::from_fn(|k| {
            mean(&|h| h.material.albedo[k]) as f32
        }));
        let world: [f64; 3] = std::array::from_fn(|k| found.iter().map(|h| h.normal[k]).sum());
        let camera_normal = unit(world).map_or([0.0, 0.0, 1.0], |n| {
            let dot = |a: [f64; 3]| a[0] * n[0] + a[1] * n[1] + a[2] * n[2];
            [dot(right) as f32, dot(up) as f32, dot(back) as f32]
        });
        normals.push(camera_normal);
        mask.push(coverage as f32);
        depth.push((coverage * mean(&|h| h.t) + (1.0 - coverage) * camera.far) as f32);
        for k in 0..4 {
            specular_weights.push(mean(&|h| h.material.specular[k]) as f32);
        }
    }
    HeadRender {
        image: IntrinsicImage {
            width: w,
            height: h,
            albedo,
            normals,
            mask,
            pose,
        },
        depth,
        specular_weights,
        hits,
        rays_per_pixel: s * s,
        camera: camera.clone(),
    }
}
