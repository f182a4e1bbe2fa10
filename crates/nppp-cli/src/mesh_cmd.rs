//! `nppp mesh`: writes a scene's mesh (e.g. a procedural object) as an OBJ,
//! so that other renderers (tools/mitsuba) can load exactly the same triangles.

use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct MeshArgs {
    /// Scene file that defines the mesh.
    #[arg(long)]
    pub scene: PathBuf,
    /// Name of the mesh in the scene's "meshes".
    #[arg(long)]
    pub mesh: String,
    /// OBJ file to write (object space, counter-clockwise front faces).
    #[arg(long)]
    pub out: PathBuf,
    /// Replace `--out` if it exists (an OBJ may be a mesh modelled by hand,
    /// so it is kept otherwise).
    #[arg(long)]
    pub overwrite: bool,
}

pub fn run(a: &MeshArgs) -> Result<()> {
    // A slip of the flags must not replace the scene (or an image) with OBJ text.
    anyhow::ensure!(
        crate::has_extension(&a.out, "obj"),
        "--out {}: the output is a Wavefront OBJ; name it *.obj",
        a.out.display()
    );
    let scene = nppp_scene::load_scene(&a.scene)?;
    // Nor may it replace any file the scene reads: the scene itself, a
    // mesh's OBJ (the one exported or another), an estimator.
    let inputs = scene.input_files();
    nppp_files::ensure_not_input("--out", &a.out, &inputs).map_err(anyhow::Error::msg)?;
    anyhow::ensure!(
        a.overwrite || std::fs::symlink_metadata(&a.out).is_err(),
        "--out {}: exists; an OBJ may be a mesh made by hand, so nppp mesh keeps it: pass \
         --overwrite to replace it, or name another file",
        a.out.display()
    );
    let Some(i) = scene.mesh_names.iter().position(|n| *n == a.mesh) else {
        anyhow::bail!(
            "{}: no mesh named \"{}\" (defined: {})",
            a.scene.display(),
            a.mesh,
            scene.mesh_names.join(", ")
        );
    };
    let m = &scene.meshes[i];
    let tri = nppp_scene::procedural::TriMesh {
        positions: m.positions.clone(),
        triangles: m.triangles.clone(),
    };
    // Into a new folder as render, gen and bake write theirs.
    nppp_files::create_parent(&a.out)
        .and_then(|_| nppp_scene::procedural::write_obj(&tri, &a.out, a.overwrite))
        .with_context(|| format!("writing {}", a.out.display()))?;
    nppp_files::note!(
        "{}: {} vertices, {} triangles",
        a.out.display(),
        m.positions.len(),
        m.triangles.len()
    );
    Ok(())
}
