//! The path tracer: two-level BVH, materials, lights, camera, the wavefront
//! integrator (diffuse bounces shaded eight paths at a time in SIMD lanes), estimator integration (queries, batched answers, next-event
//! estimation through an estimator with the network's vertex moved onto the
//! real surface, the `auto` pilot, and which instances
//! may not use theirs: other geometry inside the object's convex hull),
//! homogeneous media
//! inside translucent objects, object walks
//! (training data and the oracle), the exact film and render parts (a render
//! split by sample range over machines, merged bit for bit), error metrics,
//! image output, and huge-page backing for the large arrays rays read at
//! random (BVHs, shading normals, estimator grids).

pub mod accel;
pub mod auto;
pub mod bsdf;
pub mod bvh;
pub mod camera;
pub mod datagen;
pub mod entry;
pub mod estimator;
pub mod estimator_overlap;
pub mod film;
mod huge_pages;
pub mod image_io;
pub mod integrator;
pub mod lights;
pub mod medium;
pub mod metrics;
pub mod object_walk;
pub mod path;
mod prefix;
pub mod render;
pub mod render_part;
pub mod scene_data;
pub mod surface;
pub mod surface_snap;

pub use image_io::Image;
pub use render::{RenderOptions, RenderStats, render, render_after, render_film};
pub use scene_data::RenderScene;
