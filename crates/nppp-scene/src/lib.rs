//! Scene files (the contract of docs/scene-format.md): JSON parsing, validation
//! with errors that name the offending key path or file, the mesh sources
//! (OBJ, quad, box, icosphere, procedural objects) and the resolved,
//! render-ready [`Scene`].

mod types;
pub use types::*;
mod closed;
pub use closed::{OpenEdge, open_edge};
mod error;
pub mod hash;
mod json;
mod load;
mod obj;
pub mod procedural;
mod shapes;
pub use error::SceneError;
pub use hash::{material_content_hash, mesh_content_hash, scene_content_hash};
pub use load::{
    MAX_IMAGE_SIDE, MAX_WORLD_COORD, MESH_BYTES_PER_TRIANGLE, MIN_FLOAT_STEPS, MIN_WORLD_SIZE,
    load_scene, mesh_units_problem, parse_material, parse_mesh, parse_mesh_charged, parse_scene,
    precision_problem,
};
pub use shapes::{MAX_ICOSPHERE_SUBDIVISIONS, box_mesh, icosphere_mesh, quad_mesh};
