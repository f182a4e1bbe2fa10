//! A small Wavefront OBJ reader for exactly what docs/scene-format.md promises:
//! `v`, `vn`, and `f` in the forms `v`, `v/vt`, `v//vn`, `v/vt/vn` with
//! negative (relative) indices, polygons triangulated as the fan
//! (p0, p(i), p(i+1)) in file order.
//!
//! Written by hand rather than with tobj because the contract fixes the
//! triangulation and winding bit for bit and asks for errors with line
//! numbers, and a general loader makes its own choices on both (tobj may
//! re-triangulate, merge or reorder vertices). The rest of the format's
//! statements (`vt` contents, `o`, `g`, `s`, `usemtl`, `mtllib`, `l`, `p`,
//! free-form curves) are irrelevant to a single-material triangle mesh and
//! are skipped; `vt` lines are still counted so that texture indices can be
//! checked. A statement the format does not have is an error naming its
//! line: skipped, a mistyped `v` would shift every later index.

use crate::Mesh;
use glam::Vec3;

/// The OBJ statements (Wavefront's specification of the format) that say
/// nothing about a single-material triangle mesh and are skipped; any other
/// statement but `v`, `vn`, `vt` and `f` is an error.
const SKIPPED_STATEMENTS: &[&str] = &[
    "vp",
    "o",
    "g",
    "s",
    "mg",
    "usemtl",
    "mtllib",
    "l",
    "p",
    "cstype",
    "deg",
    "bmat",
    "step",
    "curv",
    "curv2",
    "surf",
    "parm",
    "trim",
    "hole",
    "scrv",
    "sp",
    "end",
    "con",
    "bevel",
    "c_interp",
    "d_interp",
    "lod",
    "shadow_obj",
    "trace_obj",
    "ctech",
    "stech",
    "maplib",
    "usemap",
    "call",
    "csh",
];

/// What is wrong and, when one line is to blame, its 1-based number.
#[derive(Debug)]
pub(crate) struct ObjError {
    pub line: Option<usize>,
    pub message: String,
}

fn at(line: usize, message: impl Into<String>) -> ObjError {
    ObjError {
        line: Some(line),
        message: message.into(),
    }
}

/// One corner of a face, indices already 0-based and absolute.
#[derive(Clone, Copy)]
struct Corner {
    v: usize,
    vt: Option<usize>,
    vn: Option<usize>,
}

/// Parses OBJ text. With `smooth`, every face must give a normal for every
/// corner and the mesh carries them (normalized) as shading normals.
/// `budget`: the bytes reading may hold besides the text; a file that needs
/// more is refused as it is read, not when an allocation fails.
pub(crate) fn parse_obj(text: &str, smooth: bool, budget: Option<u64>) -> Result<Mesh, ObjError> {
    // A byte-order mark (Windows editors write one) is not part of the
    // first line: left there, it hid that line's vertex.
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut positions: Vec<Vec3> = Vec::new();
    let mut normals: Vec<Vec3> = Vec::new();
    let mut texcoords = 0usize;
    let mut corners: Vec<Corner> = Vec::new();
    // (first corner, corner count, line number)
    let mut faces: Vec<(usize, usize, usize)> = Vec::new();

    // Classic Mac OS files end lines with a bare CR; `lines()` would see one
    // long line (and no faces).
    let bare_cr = !text.contains('\n') && text.contains('\r');
    let lines: Box<dyn Iterator<Item = &str>> = if bare_cr {
        Box::new(text.split('\r'))
    } else {
        Box::new(text.lines())
    };
    // What reading holds at most from here: the lists as allocated, the
    // largest one's next growth (twice its size, beside it while it is
    // copied), and the triangles the faces so far make.
    let held = |lists: [(usize, usize); 4], corners: usize, faces: usize| {
        let bytes = lists.map(|(capacity, size)| (capacity * size) as u64);
        let triangles = corners.saturating_sub(2 * faces) as u64;
        let per_triangle = 12 + if smooth { 36 } else { 0 };
        bytes.iter().sum::<u64>() + 2 * bytes.iter().max().unwrap_or(&0) + triangles * per_triangle
    };
    macro_rules! lists {
        () => {
            [
                (positions.capacity(), size_of::<Vec3>()),
                (normals.capacity(), size_of::<Vec3>()),
                (corners.capacity(), size_of::<Corner>()),
                (faces.capacity(), size_of::<(usize, usize, usize)>()),
            ]
        };
    }
    let over_budget = |need: u64, line: usize| -> Result<(), ObjError> {
        match budget {
            Some(b) if need > b => Err(at(
                line,
                format!(
                    "reading the file takes about {} by this line, more than the {} of memory \
                     available: use a coarser mesh",
                    nppp_files::format_bytes(need),
                    nppp_files::format_bytes(b)
                ),
            )),
            _ => Ok(()),
        }
    };
    let mut next_check = 1usize << 16;
    for (i, raw) in lines.enumerate() {
        let line = i + 1;
        let content = raw.split('#').next().unwrap_or("");
        let mut tokens = content.split_whitespace();
        match tokens.next() {
            Some("v") => positions.push(parse_vec3(&mut tokens, "v", line)?),
            Some("vn") => normals.push(parse_vec3(&mut tokens, "vn", line)?),
            Some("vt") => {
                // Texture coordinates are counted (faces index them), not used.
                if tokens.clone().next().is_none() {
                    return Err(at(line, "`vt` needs at least 1 coordinate"));
                }
                check_extra_numbers(&mut tokens, "vt", line, 3)?;
                texcoords += 1;
            }
            Some("f") => {
                let start = corners.len();
                for tok in tokens {
                    corners.push(parse_corner(
                        tok,
                        positions.len(),
                        texcoords,
                        normals.len(),
                        line,
                    )?);
                    // One face can hold millions of corners (a fan).
                    if corners.len().is_multiple_of(1 << 16) {
                        over_budget(held(lists!(), corners.len(), faces.len() + 1), line)?;
                    }
                }
                let n = corners.len() - start;
                if n < 3 {
                    return Err(at(
                        line,
                        format!("a face needs at least 3 vertices, this one has {n}"),
                    ));
                }
                faces.push((start, n, line));
            }
            Some(k) if SKIPPED_STATEMENTS.contains(&k) => {}
            Some(k) => {
                // A typo (`V`, `vv`) or stray bytes (a byte-order mark from
                // `cat a.obj b.obj`) would drop a vertex silently and shift
                // every later index: the mesh would render, wrong.
                return Err(at(
                    line,
                    format!(
                        "unknown statement `{}`: not one of OBJ's (nppp reads v, vn, vt and f, \
                         in lower case, and skips the others the format has: o, g, s, usemtl, \
                         mtllib, l, p, free-form curves and surfaces)",
                        k.escape_debug()
                    ),
                ));
            }
            None => {}
        }
        let items = positions.len() + normals.len() + corners.len();
        if items >= next_check {
            next_check = items + (1 << 16);
            over_budget(held(lists!(), corners.len(), faces.len()), line)?;
        }
    }

    if faces.is_empty() {
        return Err(ObjError {
            line: None,
            message: "the file has no faces (`f` lines), so the mesh would be invisible".into(),
        });
    }
    if u32::try_from(positions.len()).is_err() {
        return Err(ObjError {
            line: None,
            message: format!("{} vertices are more than 2^32 - 1", positions.len()),
        });
    }

    // Positive indices may point forward in the file, so they are checked
    // against the final counts once everything is read.
    for &(start, n, line) in &faces {
        for c in &corners[start..start + n] {
            check_index(c.v, positions.len(), "vertex", line)?;
            if let Some(t) = c.vt {
                check_index(t, texcoords, "texture coordinate", line)?;
            }
            if let Some(vn) = c.vn {
                check_index(vn, normals.len(), "normal", line)?;
            }
        }
    }

    over_budget(
        held(lists!(), corners.len(), faces.len()),
        faces.last().map_or(0, |f| f.2),
    )?;
    let triangle_count: usize = faces.iter().map(|&(_, n, _)| n - 2).sum();
    let mut triangles = Vec::with_capacity(triangle_count);
    let mut shading = smooth.then(|| Vec::with_capacity(triangle_count));
    for &(start, n, line) in &faces {
        let face = &corners[start..start + n];
        let face_normals = match &shading {
            Some(_) => Some(face_normals(face, &normals, line)?),
            None => None,
        };
        for k in 1..n - 1 {
            // Indices fit in u32: checked against positions.len() above.
            triangles.push([face[0].v as u32, face[k].v as u32, face[k + 1].v as u32]);
            if let (Some(out), Some(fnorm)) = (shading.as_mut(), face_normals.as_ref()) {
                out.push([fnorm[0], fnorm[k], fnorm[k + 1]]);
            }
        }
    }
    // Zero-area triangles are never hit: a file of nothing else renders as
    // nothing, like a file without faces.
    let has_area = |t: &[u32; 3]| {
        // In f64: the squared length overflows f32 for edges past about 4e9.
        let [a, b, c] = t.map(|i| positions[i as usize].as_dvec3());
        let n = (b - a).cross(c - a).length_squared();
        n > 0.0 && n.is_finite()
    };
    if !triangles.iter().any(has_area) {
        return Err(ObjError {
            line: None,
            message: format!(
                "all {} triangles have zero area (their corners are collinear or repeated), so \
                 the mesh would be invisible",
                triangles.len()
            ),
        });
    }
    Ok(Mesh {
        positions,
        triangles,
        shading_normals: shading,
    })
}

fn parse_vec3<'a>(
    tokens: &mut impl Iterator<Item = &'a str>,
    what: &str,
    line: usize,
) -> Result<Vec3, ObjError> {
    let mut xyz = [0f32; 3];
    for (k, slot) in xyz.iter_mut().enumerate() {
        let tok = tokens.next().ok_or_else(|| {
            at(
                line,
                format!("`{what}` needs 3 coordinates, found only {k}"),
            )
        })?;
        let value: f32 = tok
            .parse()
            .map_err(|_| at(line, format!("`{what}` coordinate `{tok}` is not a number")))?;
        if !value.is_finite() {
            return Err(at(
                line,
                format!("`{what}` coordinate `{tok}` is not finite as a 32-bit float"),
            ));
        }
        *slot = value;
    }
    // Further numbers (a `w`, or vertex colours some exporters append) carry
    // nothing a flat-coloured triangle mesh uses, but anything else there is
    // a damaged line.
    check_extra_numbers(tokens, what, line, 4)?;
    Ok(Vec3::from_array(xyz))
}

/// The rest of a line whose values nppp does not use: at most `max`
/// tokens, each a finite number.
fn check_extra_numbers<'a>(
    tokens: &mut impl Iterator<Item = &'a str>,
    what: &str,
    line: usize,
    max: usize,
) -> Result<(), ObjError> {
    for (k, tok) in tokens.enumerate() {
        if k == max {
            return Err(at(
                line,
                format!("`{what}` has more values than an OBJ line holds (`{tok}`)"),
            ));
        }
        if !tok.parse::<f32>().is_ok_and(f32::is_finite) {
            return Err(at(
                line,
                format!("`{what}` value `{tok}` is not a finite number"),
            ));
        }
    }
    Ok(())
}

/// Parses `v`, `v/vt`, `v//vn` or `v/vt/vn`, resolving negative indices
/// against the counts defined so far, as the OBJ format says.
fn parse_corner(
    tok: &str,
    nv: usize,
    nvt: usize,
    nvn: usize,
    line: usize,
) -> Result<Corner, ObjError> {
    let parts: Vec<&str> = tok.split('/').collect();
    let malformed = || {
        at(
            line,
            format!("face vertex `{tok}` is not one of v, v/vt, v//vn, v/vt/vn"),
        )
    };
    let (v, vt, vn) = match parts.as_slice() {
        [v] => (*v, None, None),
        [v, vt] => (*v, Some(*vt), None),
        [v, "", vn] => (*v, None, Some(*vn)),
        [v, vt, vn] => (*v, Some(*vt), Some(*vn)),
        _ => return Err(malformed()),
    };
    if v.is_empty() || vt == Some("") || vn == Some("") {
        return Err(malformed());
    }
    Ok(Corner {
        v: resolve(v, nv, "vertex", line)?,
        vt: vt
            .map(|t| resolve(t, nvt, "texture coordinate", line))
            .transpose()?,
        vn: vn.map(|n| resolve(n, nvn, "normal", line)).transpose()?,
    })
}

fn resolve(tok: &str, defined: usize, what: &str, line: usize) -> Result<usize, ObjError> {
    let i: i64 = tok.parse().map_err(|e: std::num::ParseIntError| {
        use std::num::IntErrorKind::{NegOverflow, PosOverflow};
        match e.kind() {
            PosOverflow | NegOverflow => at(line, format!("{what} index `{tok}` is too large")),
            _ => at(line, format!("{what} index `{tok}` is not an integer")),
        }
    })?;
    if i > 0 {
        // Stored 0-based; the range check happens after the whole file is read.
        usize::try_from(i - 1).map_err(|_| at(line, format!("{what} index {i} is too large")))
    } else if i < 0 {
        let back = usize::try_from(i.unsigned_abs()).unwrap_or(usize::MAX);
        defined.checked_sub(back).ok_or_else(|| {
            at(
                line,
                format!(
                    "relative {what} index {i} points before the first {what}: only {defined} defined so far"
                ),
            )
        })
    } else {
        Err(at(
            line,
            format!("{what} index 0 is invalid (OBJ indices start at 1)"),
        ))
    }
}

fn check_index(i: usize, count: usize, what: &str, line: usize) -> Result<(), ObjError> {
    if i < count {
        Ok(())
    } else {
        Err(at(
            line,
            format!(
                "{what} index {} points past the file's {count} {}",
                i as u128 + 1,
                plural(what, count)
            ),
        ))
    }
}

fn plural(what: &str, count: usize) -> String {
    match (what, count) {
        (_, 1) => what.to_string(),
        ("vertex", _) => "vertices".to_string(),
        _ => format!("{what}s"),
    }
}

/// The face's corner normals, normalized; `smooth` demands one per corner.
fn face_normals(face: &[Corner], normals: &[Vec3], line: usize) -> Result<Vec<Vec3>, ObjError> {
    face.iter()
        .map(|c| {
            let vn = c.vn.ok_or_else(|| {
                at(
                    line,
                    "the mesh is \"smooth\": true but this face has no vertex normals (use v//vn or v/vt/vn)",
                )
            })?;
            // Scaled first: a finite normal near f32::MAX has an infinite
            // squared length, and is a direction all the same.
            let n = normals[vn];
            let big = n.abs().max_element();
            (n / big).try_normalize().ok_or_else(|| {
                at(
                    line,
                    format!("normal {} has zero length and cannot be used for smooth shading", vn + 1),
                )
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fan of `n` triangles in one face: 1 corner a triangle.
    fn fan(n: usize) -> String {
        let mut s = String::new();
        for k in 0..n + 2 {
            let a = k as f32 * 0.001;
            s += &format!("v {} {} 0\n", a.cos(), a.sin());
        }
        s += "f";
        for k in 1..=n + 2 {
            s += &format!(" {k}");
        }
        s + "\n"
    }

    /// The format's other statements are skipped; one it does not have (a
    /// typo, stray bytes before a `v`) is refused with its line, rather
    /// than skipped with every later index shifted.
    #[test]
    fn unknown_statements_are_refused_known_ones_skipped() {
        let ok = "mtllib m.mtl\no knot\ng a\ns 1\nusemtl red\nv 0 0 0\nv 1 0 0\nv 0 1 0\n\
                  vp 0.5\nl 1 2\np 1\nf 1 2 3\n";
        assert_eq!(parse_obj(ok, false, None).unwrap().triangles.len(), 1);
        for (bad, what) in [
            ("V 0 0 0", "`V`"),
            ("vv 0 0 0", "`vv`"),
            ("\u{feff}v 0 0 0", "`\\u{feff}v`"),
            ("F 1 2 3", "`F`"),
        ] {
            let text = format!("v 0 0 0\nv 1 0 0\n{bad}\nv 0 1 0\nf 1 2 3\n");
            let err = parse_obj(&text, false, None).unwrap_err();
            assert_eq!(err.line, Some(3), "{bad:?}");
            assert!(
                err.message.contains(&format!("unknown statement {what}")),
                "{bad:?}: {}",
                err.message
            );
        }
    }

    /// A file that needs more than the budget is refused while it is read,
    /// naming the line it got to; the same file within budget reads whole.
    #[test]
    fn a_file_past_its_memory_budget_is_refused_as_it_is_read() {
        let text = fan(100_000);
        let err = parse_obj(&text, false, Some(1 << 20)).unwrap_err();
        assert!(err.message.contains("memory available"), "{}", err.message);
        assert!(err.line.is_some());
        let mesh = parse_obj(&text, false, Some(1 << 30)).unwrap();
        assert_eq!(mesh.triangles.len(), 100_000);
        assert_eq!(parse_obj(&text, false, None).unwrap(), mesh);
    }
}
