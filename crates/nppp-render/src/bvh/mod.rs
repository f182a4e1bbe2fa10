//! 8-wide BVHs laid out for CPU traversal: one per mesh ([`MeshBvh`]) and
//! one over instance boxes ([`InstanceBvh`], the TLAS).
//!
//! obvhs builds the trees (PLOC plus reinsertion, a binary BVH of good
//! quality); this module collapses them to eight children per node and
//! stores them the way a CPU likes to read them: each node holds its
//! children's boxes as full-precision SoA lanes, tested in one 8-lane pass
//! per axis (`wide::f32x8`: one AVX instruction where the build targets it,
//! two SSE halves in the portable build), and a mesh leaf holds its
//! triangles four at a time in SoA packets, tested in one pass. obvhs' own
//! CPU traversal walks a compressed 8-wide GPU layout (quantized boxes,
//! decoded per node). `cargo bench --bench blas_layout` on the default
//! scene, 2-core AMD EPYC (AVX2), native build, throughput over obvhs' CWBVH
//! on the same rays: 1.44x-1.47x primary, 1.58x incoherent, 1.62x-1.66x
//! shadow rays; the 4-wide layout this replaced (same collapse, four
//! children, SSE) measured 1.07x-1.12x, 1.20x-1.21x and 1.45x-1.47x in the
//! same session (the default scene renders in 0.89x the time with plain PT,
//! cornell-glass in 0.87x). Leaves of up to 8 triangles measured best with
//! the 4-wide nodes (4: 0.92x to 0.95x of that, 12: 0.93x to 1.05x).
//!
//! Closest hits are exact in the sense that matters to the renderer: the
//! nearest triangle by the same Möller-Trumbore test the renderer always
//! used (a property test checks it against brute force); box tests are
//! conservative (far distances padded by a few ulps) so a triangle is never
//! culled by rounding.

use glam::{Vec3, Vec3A, Vec4};
use obvhs::{BvhBuildParams, aabb::Aabb, bvh2::Bvh2, triangle::Triangle};
use std::mem::MaybeUninit;
use std::ops::Range;
use std::time::Duration;
use wide::f32x8;

use crate::huge_pages::HugeArray;

/// Mesh leaves hold at most this many triangles (two packets).
const MESH_LEAF_MAX: u32 = 8;
/// TLAS leaves hold one instance: its box is tested before its BLAS is
/// (a box test is far cheaper than moving a ray into an instance).
const INSTANCE_LEAF_MAX: u32 = 1;
/// Child code bit marking a leaf: `LEAF | (count - 1) << 28 | first`, where
/// count and first address the owner's payload (triangle packets or items).
const LEAF: u32 = 1 << 31;
const COUNT_SHIFT: u32 = 28;
const FIRST_MASK: u32 = (1 << COUNT_SHIFT) - 1;

/// The payload range (triangle packets or items) of leaf code `code`.
#[inline(always)]
fn leaf_items(code: u32) -> Range<usize> {
    let first = (code & FIRST_MASK) as usize;
    let count = ((code & !LEAF) >> COUNT_SHIFT) as usize + 1;
    first..first + count
}

/// An unused child slot (its box is empty, so it is never entered).
const EMPTY: u32 = u32::MAX;
/// Children per node: eight, tested in one 8-lane pass per axis.
const NODE_WIDTH: usize = 8;
/// Stack entries a traversal of a tree of depth 63 can need
/// (`NODE_WIDTH - 1` per level + 1).
const INLINE_STACK: usize = (NODE_WIDTH - 1) * 63 + 1;
/// Far-distance padding of box tests: 3 ulp-scale relative errors of the
/// slab arithmetic (pbrt's `1 + 2 * gamma(3)`), so rounding never culls a box.
const FAR_PAD: f32 = 1.0 + 2.0 * (3.0 * f32::EPSILON * 0.5) / (1.0 - 3.0 * f32::EPSILON * 0.5);

/// The children's boxes, SoA (one array of eight per axis), and their
/// codes (inner node index or leaf).
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct Node {
    lo: [[f32; NODE_WIDTH]; 3],
    hi: [[f32; NODE_WIDTH]; 3],
    child: [u32; NODE_WIDTH],
}

/// Four triangles, SoA: a vertex and two edges each. Unused lanes have zero
/// edges (a zero determinant never hits).
#[derive(Clone, Copy, Debug)]
#[repr(C, align(16))]
struct Tri4 {
    v0: [Vec4; 3],
    e1: [Vec4; 3],
    e2: [Vec4; 3],
    /// Original triangle index of each lane.
    prim: [u32; 4],
}

/// A closest hit inside one mesh: distance, original triangle, barycentrics.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeshHit {
    pub t: f32,
    pub prim: u32,
    pub b1: f32,
    pub b2: f32,
    /// e1 x e2 of the triangle (unnormalized, the BVH's space): read from
    /// the packet just tested, so shading needs no per-triangle normal table
    /// (a cache miss per hit).
    pub ng: Vec3,
}

/// Nodes of an 8-wide tree; what its leaves hold is its owner's business.
struct Tree {
    nodes: HugeArray<Node>,
    /// Code of the root: node 0, or `EMPTY` for no input.
    root: u32,
    /// Deepest level of the tree (the root is level 1); sizes the stack.
    depth: u32,
}

/// The 8-wide BVH of one mesh. Empty meshes have no nodes and never hit.
pub struct MeshBvh {
    tree: Tree,
    packets: HugeArray<Tri4>,
}

/// The TLAS: an 8-wide BVH over instance boxes.
pub struct InstanceBvh {
    tree: Tree,
    /// Item (instance box) indices, leaf by leaf.
    items: Vec<u32>,
}

/// A ray prepared for the SIMD tests.
struct RaySimd {
    o: [Vec4; 3],
    d: [Vec4; 3],
    inv: [Vec4; 3],
    /// Per axis: does the ray run towards negative coordinates?
    neg: [bool; 3],
}

impl RaySimd {
    #[inline(always)]
    fn new(o: Vec3A, d: Vec3A) -> Self {
        // A zero component would make 0 * inf = NaN in the slab test; a tiny
        // one of the same sign (-0.0 included) gives the limit it wants.
        let safe = |c: f32| {
            if c.abs() < 1e-30 {
                1.0 / 1e-30f32.copysign(c)
            } else {
                1.0 / c
            }
        };
        let inv = Vec3A::new(safe(d.x), safe(d.y), safe(d.z));
        Self {
            o: [Vec4::splat(o.x), Vec4::splat(o.y), Vec4::splat(o.z)],
            d: [Vec4::splat(d.x), Vec4::splat(d.y), Vec4::splat(d.z)],
            inv: [Vec4::splat(inv.x), Vec4::splat(inv.y), Vec4::splat(inv.z)],
            // From the inverse, not from `d`: a -0.0 component has a negative
            // inverse, and `-0.0 < 0.0` is false (the slabs would be swapped
            // wrongly and every box missed).
            neg: [inv.x < 0.0, inv.y < 0.0, inv.z < 0.0],
        }
    }

    /// Entry distances of the eight children and a bit mask of those entered
    /// within (tmin, tmax).
    #[inline(always)]
    fn boxes(&self, n: &Node, tmin: f32, tmax: f32) -> ([f32; NODE_WIDTH], u32) {
        let mut near = f32x8::splat(tmin);
        let mut far = f32x8::splat(tmax);
        for a in 0..3 {
            let (lo, hi) = if self.neg[a] {
                (n.hi[a], n.lo[a])
            } else {
                (n.lo[a], n.hi[a])
            };
            let (o, inv) = (f32x8::splat(self.o[a].x), f32x8::splat(self.inv[a].x));
            // `fast_max`/`fast_min` are the plain max/min instructions, as
            // the SSE tests use: a NaN slab never enters a box.
            near = near.fast_max((f32x8::from(lo) - o) * inv);
            far = far.fast_min((f32x8::from(hi) - o) * inv * f32x8::splat(FAR_PAD));
        }
        (near.to_array(), near.simd_le(far).to_bitmask())
    }

    /// Möller-Trumbore on four triangles: lanes hit in (tmin, tmax), and
    /// their t, b1, b2.
    #[inline(always)]
    fn triangles(&self, p: &Tri4, tmin: f32, tmax: f32) -> (u32, Vec4, Vec4, Vec4) {
        let [dx, dy, dz] = self.d;
        let [e1x, e1y, e1z] = p.e1;
        let [e2x, e2y, e2z] = p.e2;
        let px = dy * e2z - dz * e2y;
        let py = dz * e2x - dx * e2z;
        let pz = dx * e2y - dy * e2x;
        let det = e1x * px + e1y * py + e1z * pz;
        let inv = Vec4::ONE / det;
        let sx = self.o[0] - p.v0[0];
        let sy = self.o[1] - p.v0[1];
        let sz = self.o[2] - p.v0[2];
        let b1 = (sx * px + sy * py + sz * pz) * inv;
        let qx = sy * e1z - sz * e1y;
        let qy = sz * e1x - sx * e1z;
        let qz = sx * e1y - sy * e1x;
        let b2 = (dx * qx + dy * qy + dz * qz) * inv;
        let t = (e2x * qx + e2y * qy + e2z * qz) * inv;
        let zero = Vec4::ZERO;
        // Written so that NaN anywhere fails: every test is an ordered compare.
        let ok = det.abs().cmpgt(zero)
            & det.abs().cmplt(Vec4::splat(f32::INFINITY))
            & b1.cmpge(zero)
            & b1.cmple(Vec4::ONE)
            & b2.cmpge(zero)
            & (b1 + b2).cmple(Vec4::ONE)
            & t.cmpgt(Vec4::splat(tmin))
            & t.cmplt(Vec4::splat(tmax));
        (ok.bitmask(), t, b1, b2)
    }
}

/// The traversal stack: inline for trees up to depth 63 (every real mesh),
/// on the heap for deeper ones (degenerate inputs), never overflowing.
trait Stack {
    fn push(&mut self, e: (u32, f32));
    fn pop(&mut self) -> Option<(u32, f32)>;
}

/// A fixed array used as a stack; only the first `len` entries are ever
/// read, so it is left uninitialised.
struct InlineStack {
    len: usize,
    items: [MaybeUninit<(u32, f32)>; INLINE_STACK],
}

impl InlineStack {
    #[inline(always)]
    fn new() -> Self {
        // `const { .. }` matters: `[MaybeUninit::uninit(); N]` or a whole
        // `MaybeUninit<[_; N]>` in a struct literal are zeroed by rustc 1.95
        // (a 1.5 KiB memset per ray, 5% of a render).
        Self {
            len: 0,
            items: [const { MaybeUninit::uninit() }; INLINE_STACK],
        }
    }
}

impl Stack for InlineStack {
    #[inline(always)]
    fn push(&mut self, e: (u32, f32)) {
        // Bounds-checked: a tree deeper than the stack was sized for would
        // be a panic, not memory corruption (the traversal routes depth >= 64
        // to the heap stack, so it cannot happen).
        self.items[self.len] = MaybeUninit::new(e);
        self.len += 1;
    }
    #[inline(always)]
    fn pop(&mut self) -> Option<(u32, f32)> {
        if self.len == 0 {
            None
        } else {
            self.len -= 1;
            // SAFETY: entries below `len` were written by `push`.
            Some(unsafe { self.items[self.len].assume_init() })
        }
    }
}

impl Stack for Vec<(u32, f32)> {
    fn push(&mut self, e: (u32, f32)) {
        Vec::push(self, e);
    }
    fn pop(&mut self) -> Option<(u32, f32)> {
        Vec::pop(self)
    }
}

/// Where a tree's leaf payload lives, for prefetching only (never read).
#[derive(Clone, Copy)]
struct Payload {
    base: *const u8,
    stride: usize,
}

impl Payload {
    fn of<T>(items: &[T]) -> Self {
        Self {
            base: items.as_ptr() as *const u8,
            stride: size_of::<T>(),
        }
    }
}

/// Prefetches item `i` of `items` (nothing if out of range).
#[inline(always)]
pub(crate) fn prefetch_item<T>(items: &[T], i: usize) {
    if let Some(x) = items.get(i) {
        prefetch_range((x as *const T).cast(), size_of::<T>());
    }
}

/// Prefetches every cache line of the `bytes` bytes at `addr` (a node, or
/// a leaf's triangle packets). A prefetch never faults, so any address is
/// fine. Prefetching only a node's or a leaf's first two lines, as before,
/// left its later lines to stall the box and triangle tests: whole nodes
/// and leaves measured 1.02x-1.06x the throughput (`blas_layout`, AVX-512).
#[inline(always)]
pub(crate) fn prefetch_range(addr: *const u8, bytes: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        let end = addr as usize + bytes;
        let mut line = addr as usize & !63;
        while line < end {
            // SAFETY: prefetches do not access memory architecturally; they
            // cannot fault, whatever the address.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(line as *const i8) };
            line += 64;
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (addr, bytes);
}

/// What a leaf visit asks of the traversal.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Visit {
    Continue,
    Stop,
}

/// obvhs' medium build with PLOC's wider neighbour search (High instead of
/// Medium) from tree depth 2 on (its default 3). `cargo bench --bench
/// blas_layout`, 2-core AMD EPYC with AVX-512, throughput over the medium
/// build: primary rays 1.04x-1.10x, incoherent 1.05x-1.08x, shadow rays
/// 1.20x-1.25x, for a build 1.15x as long (0.24 s for the default scene's
/// 327,680 triangles). The slow build (pre-splits, reinsertion 0.2) made
/// no faster renders for 2.5x the build time.
fn build_params() -> BvhBuildParams {
    BvhBuildParams {
        ploc_search_distance: obvhs::ploc::PlocSearchDistance::High,
        search_depth_threshold: 2,
        // Single-primitive leaves: this module makes its own leaves.
        max_prims_per_leaf: 1,
        ..BvhBuildParams::medium_build()
    }
}

/// Groups of more identical boxes than this get their ties broken
/// ([`break_box_ties`]). A quad's two triangles share a box, so pairs are
/// common and harmless.
const TIED_GROUP_MIN: usize = 3;

/// Widens the boxes of every group of more than two identical boxes, each
/// side of each box by its own pseudo-random amount, so that obvhs' PLOC
/// builder sees different merge costs. PLOC merges mutual nearest
/// neighbours, and among n equal costs it finds one mutual pair per pass:
/// n passes over n nodes. A mesh shrunk until its vertices round together
/// (a knot scaled by 1e-4 at x = 278 never finished building) or thousands
/// of instances placed at one spot took quadratic time. Each side moves by
/// its own amount, so the widened boxes do not nest (nested boxes would
/// merge into a chain as deep as the group). Widened boxes still contain
/// their primitives, so traversal stays exact; boxes with no twin (every
/// committed scene's, bar the pairs) are left as they are, bit for bit.
fn break_box_ties(aabbs: &mut [Aabb]) {
    let key = |b: &Aabb| {
        let (lo, hi) = (b.min.to_array(), b.max.to_array());
        [lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]].map(f32::to_bits)
    };
    // Group sizes by sorting the keys (no hashing of every triangle).
    let mut keys: Vec<([u32; 6], u32)> = aabbs
        .iter()
        .enumerate()
        .map(|(i, b)| (key(b), i as u32))
        .collect();
    keys.sort_unstable();
    let mut start = 0;
    while start < keys.len() {
        let mut end = start + 1;
        while end < keys.len() && keys[end].0 == keys[start].0 {
            end += 1;
        }
        if end - start >= TIED_GROUP_MIN {
            for &(_, i) in &keys[start..end] {
                let b = &mut aabbs[i as usize];
                // Steps of at least a few ulps of the box's farthest
                // coordinate (a smaller widening would round away) or
                // 1/4096 of its size; 1 to 256 of them per side, from a
                // hash of the index (SplitMix64's finalizer).
                let reach = b.min.abs().max(b.max.abs()).max_element();
                let step = (4.0 * nppp_geom::float_step(reach))
                    .max((b.max - b.min).max_element() / 4096.0)
                    .max(f32::MIN_POSITIVE);
                let mut h = u64::from(i).wrapping_add(0x9e37_79b9_7f4a_7c15);
                h = (h ^ (h >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
                h = (h ^ (h >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
                h ^= h >> 31;
                let side = |k: u32| step * (1 + ((h >> (8 * k)) & 0xff)) as f32;
                let lo = Vec3A::new(side(0), side(1), side(2));
                let hi = Vec3A::new(side(3), side(4), side(5));
                *b = Aabb::new(b.min - lo, b.max + hi);
            }
        }
        start = end;
    }
}

impl MeshBvh {
    /// Builds the BVH of `tris` (any count, including zero).
    pub fn build(tris: &[Triangle]) -> Self {
        let mut packets = Vec::new();
        let tree = if tris.is_empty() {
            Tree::empty()
        } else {
            let mut aabbs: Vec<Aabb> = tris.iter().map(Triangle::aabb).collect();
            break_box_ties(&mut aabbs);
            let mut params = build_params();
            // A mesh whose vertices round together (a small object far from
            // the origin: a knot 600 float steps across at x = 7,000) has
            // most triangles without area, and obvhs' reinsertion pass,
            // which moves nodes to where they cost least, spent 30-80 s
            // among their equal costs. Its trees are not worth the pass.
            let flat = tris
                .iter()
                .filter(|t| (t.v1 - t.v0).cross(t.v2 - t.v0) == Vec3A::ZERO)
                .count();
            if flat * 10 > tris.len() {
                params.reinsertion_batch_ratio = 0.0;
            }
            let bvh2 = obvhs::bvh2::builder::build_bvh2(&aabbs, params, &mut Duration::default());
            Collapser::new(&bvh2, MESH_LEAF_MAX).run(&mut |prims: &[u32]| {
                let first = packets.len();
                for chunk in prims.chunks(4) {
                    packets.push(Tri4::pack(chunk, tris));
                }
                (first, packets.len() - first)
            })
        };
        Self {
            tree,
            packets: HugeArray::new(packets),
        }
    }

    /// Closest hit along a ray with unit direction in (tmin, tmax).
    #[inline]
    pub fn intersect(&self, o: Vec3A, d: Vec3A, tmin: f32, tmax: f32) -> Option<MeshHit> {
        if self.tree.root == EMPTY {
            return None;
        }
        let ray = RaySimd::new(o, d);
        // (packet, lane, b1, b2) of the closest hit so far; the hit itself
        // is assembled after the walk, which keeps this closure small enough
        // to be inlined into it (assembling here cost 12% of a render).
        let mut best: Option<(usize, usize, f32, f32)> = None;
        let mut t_best = tmax;
        self.tree.traverse(
            &ray,
            tmin,
            tmax,
            true,
            self.payload(),
            |leaf, tmax: &mut f32| {
                for k in leaf {
                    let (mut mask, t, b1, b2) = ray.triangles(&self.packets[k], tmin, *tmax);
                    while mask != 0 {
                        let lane = mask.trailing_zeros() as usize;
                        mask &= mask - 1;
                        if t[lane] < *tmax {
                            *tmax = t[lane];
                            best = Some((k, lane, b1[lane], b2[lane]));
                        }
                    }
                }
                t_best = *tmax;
                Visit::Continue
            },
        );
        let (k, lane, b1, b2) = best?;
        let p = &self.packets[k];
        let e = |v: &[Vec4; 3]| Vec3::new(v[0][lane], v[1][lane], v[2][lane]);
        Some(MeshHit {
            t: t_best,
            prim: p.prim[lane],
            b1,
            b2,
            ng: e(&p.e1).cross(e(&p.e2)),
        })
    }

    /// Whether the ray (t > 0) enters any of the root's child boxes: false
    /// means it certainly misses the mesh. One node test, no traversal.
    #[inline]
    pub fn may_hit(&self, o: Vec3A, d: Vec3A) -> bool {
        self.tree.root != EMPTY
            && RaySimd::new(o, d)
                .boxes(
                    &self.tree.nodes[self.tree.root as usize],
                    0.0,
                    f32::INFINITY,
                )
                .1
                != 0
    }

    /// True if any triangle lies in (tmin, tmax); stops at the first found.
    #[inline]
    pub fn occluded(&self, o: Vec3A, d: Vec3A, tmin: f32, tmax: f32) -> bool {
        if self.tree.root == EMPTY {
            return false;
        }
        let ray = RaySimd::new(o, d);
        let mut hit = false;
        self.tree
            .traverse(&ray, tmin, tmax, false, self.payload(), |leaf, tmax| {
                for p in &self.packets[leaf] {
                    if ray.triangles(p, tmin, *tmax).0 != 0 {
                        hit = true;
                        return Visit::Stop;
                    }
                }
                Visit::Continue
            });
        hit
    }

    fn payload(&self) -> Payload {
        Payload::of(&self.packets)
    }

    /// Calls `f` with the corners of each triangle under the boxes `keep`
    /// accepts (`keep(lo, hi)`, the BVH's space), until `f` returns false.
    /// A region query for building scenes, not for rays. The corners are
    /// the packets' (`v0`, `v0 + e1`, `v0 + e2`), within rounding of the
    /// mesh's.
    pub fn visit_triangles(
        &self,
        keep: impl Fn(Vec3, Vec3) -> bool,
        mut f: impl FnMut([Vec3; 3]) -> bool,
    ) {
        self.tree.visit_leaves(keep, |leaf| {
            for p in &self.packets[leaf] {
                for lane in 0..4 {
                    let v = |a: &[Vec4; 3]| Vec3::new(a[0][lane], a[1][lane], a[2][lane]);
                    let (v0, e1, e2) = (v(&p.v0), v(&p.e1), v(&p.e2));
                    // An unused lane (and a point, which no ray hits).
                    if e1 == Vec3::ZERO && e2 == Vec3::ZERO {
                        continue;
                    }
                    if !f([v0, v0 + e1, v0 + e2]) {
                        return false;
                    }
                }
            }
            true
        });
    }

    /// Memory of nodes and triangle packets, in bytes.
    pub fn memory_bytes(&self) -> usize {
        self.tree.nodes.len() * size_of::<Node>() + self.packets.len() * size_of::<Tri4>()
    }
}

impl InstanceBvh {
    /// Builds the BVH over boxes `(lo, hi)`; items are their indices.
    pub fn build(boxes: &[(Vec3, Vec3)]) -> Self {
        let mut items = Vec::new();
        let tree = if boxes.is_empty() {
            Tree::empty()
        } else {
            let mut aabbs: Vec<Aabb> = boxes
                .iter()
                .map(|(lo, hi)| Aabb::new((*lo).into(), (*hi).into()))
                .collect();
            break_box_ties(&mut aabbs);
            let bvh2 =
                obvhs::bvh2::builder::build_bvh2(&aabbs, build_params(), &mut Duration::default());
            Collapser::new(&bvh2, INSTANCE_LEAF_MAX).run(&mut |prims: &[u32]| {
                let first = items.len();
                items.extend_from_slice(prims);
                (first, prims.len())
            })
        };
        Self { tree, items }
    }

    /// Calls `f` with each item whose box `keep` accepts (`keep(lo, hi)`;
    /// every box above it must pass too, so `keep` should accept a box
    /// whenever it accepts one inside it). A region query for building
    /// scenes, not for rays.
    pub fn visit_items(&self, keep: impl Fn(Vec3, Vec3) -> bool, mut f: impl FnMut(u32)) {
        self.tree.visit_leaves(keep, |leaf| {
            self.items[leaf].iter().for_each(|&i| f(i));
            true
        });
    }

    /// Calls `visit(item, tmax)` for the items whose boxes the ray (unit
    /// direction) enters within (0, tmax), nearest subtree first when
    /// `ordered`. `visit` may lower `tmax` (a closest-hit query) or stop.
    #[inline]
    pub fn traverse(
        &self,
        o: Vec3A,
        d: Vec3A,
        tmax: f32,
        ordered: bool,
        mut visit: impl FnMut(u32, &mut f32) -> Visit,
    ) {
        if self.tree.root == EMPTY {
            return;
        }
        let ray = RaySimd::new(o, d);
        let payload = Payload::of(&self.items);
        self.tree
            .traverse(&ray, 0.0, tmax, ordered, payload, |leaf, tmax| {
                for &item in &self.items[leaf] {
                    if visit(item, tmax) == Visit::Stop {
                        return Visit::Stop;
                    }
                }
                Visit::Continue
            });
    }
}

thread_local! {
    /// Nodes and leaves visited by every traversal on this thread: a
    /// deterministic measure of traversal work (a render's time is not),
    /// read per tile by the renderer. Added to once per traversal.
    static NODE_VISITS: std::cell::Cell<u64> = const { std::cell::Cell::new(0) };
    /// The leaves among them (a mesh leaf's triangle packets, a TLAS leaf's
    /// instance), counted apart: timed renders fitted a leaf visit at a
    /// small fraction of an inner node's (its packets were prefetched while
    /// its parent was tested), so the `auto` cost model counts inner nodes.
    static LEAF_VISITS: std::cell::Cell<u64> = const { std::cell::Cell::new(0) };
}

/// Nodes and leaves this thread's traversals have visited so far (take the
/// difference around a piece of work).
pub fn node_visits() -> u64 {
    NODE_VISITS.with(|c| c.get())
}

/// Leaves this thread's traversals have entered so far (a part of
/// [`node_visits`]).
pub fn leaf_visits() -> u64 {
    LEAF_VISITS.with(|c| c.get())
}

impl Tree {
    fn empty() -> Self {
        Self {
            nodes: HugeArray::new(vec![]),
            root: EMPTY,
            depth: 0,
        }
    }

    /// Depth-first walk of the subtrees whose boxes `keep` accepts
    /// (`keep(lo, hi)`); `leaf(range)` gets each such leaf's payload range
    /// and returns false to stop. The root is always a node, so every leaf
    /// has its box tested. For region queries while building scenes: it
    /// allocates its stack.
    fn visit_leaves(
        &self,
        keep: impl Fn(Vec3, Vec3) -> bool,
        mut leaf: impl FnMut(Range<usize>) -> bool,
    ) {
        if self.root == EMPTY {
            return;
        }
        let mut stack = vec![self.root];
        while let Some(code) = stack.pop() {
            if code & LEAF != 0 {
                if !leaf(leaf_items(code)) {
                    return;
                }
                continue;
            }
            let n = &self.nodes[code as usize];
            for c in 0..NODE_WIDTH {
                let lo = Vec3::new(n.lo[0][c], n.lo[1][c], n.lo[2][c]);
                let hi = Vec3::new(n.hi[0][c], n.hi[1][c], n.hi[2][c]);
                if n.child[c] != EMPTY && keep(lo, hi) {
                    stack.push(n.child[c]);
                }
            }
        }
    }

    /// Depth-first traversal; `leaf(range, tmax)` gets each entered leaf's
    /// payload range and may lower `tmax` or stop. `ordered` visits children
    /// nearest first (closest hits); shadow rays skip the sorting.
    #[inline(always)]
    fn traverse(
        &self,
        ray: &RaySimd,
        tmin: f32,
        tmax: f32,
        ordered: bool,
        payload: Payload,
        mut leaf: impl FnMut(Range<usize>, &mut f32) -> Visit,
    ) {
        let mut tmax = tmax;
        let mut visits = [0u32; 2];
        if self.depth < 64 {
            let stack = &mut InlineStack::new();
            self.walk(
                ray,
                tmin,
                &mut tmax,
                ordered,
                payload,
                stack,
                &mut leaf,
                &mut visits,
            );
        } else {
            let stack = &mut Vec::new();
            self.walk(
                ray,
                tmin,
                &mut tmax,
                ordered,
                payload,
                stack,
                &mut leaf,
                &mut visits,
            );
        }
        NODE_VISITS.with(|c| c.set(c.get() + visits[0] as u64));
        LEAF_VISITS.with(|c| c.set(c.get() + visits[1] as u64));
    }

    /// Asks the cache for a child the ray entered while the others are
    /// sorted and pushed: traversal is bound by memory latency (the node and
    /// packet loads were a third of closest-hit time), and a popped child
    /// is then already on its way.
    #[inline(always)]
    fn prefetch(&self, code: u32, payload: Payload) {
        if code & LEAF == 0 {
            // The whole node: boxes and child codes span four lines.
            let addr = self.nodes.as_ptr().wrapping_add(code as usize) as *const u8;
            prefetch_range(addr, size_of::<Node>());
        } else {
            // Every packet of the leaf (a packet is 160 bytes, so even one
            // spans three lines).
            let items = leaf_items(code);
            let addr = payload.base.wrapping_add(items.start * payload.stride);
            prefetch_range(addr, items.len() * payload.stride);
        }
    }

    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn walk<S: Stack, F: FnMut(Range<usize>, &mut f32) -> Visit>(
        &self,
        ray: &RaySimd,
        tmin: f32,
        tmax: &mut f32,
        ordered: bool,
        payload: Payload,
        stack: &mut S,
        leaf: &mut F,
        visits: &mut [u32; 2],
    ) {
        let mut code = self.root;
        loop {
            visits[0] += 1;
            if code & LEAF == 0 {
                let node = &self.nodes[code as usize];
                let (near, mask) = ray.boxes(node, tmin, *tmax);
                if mask != 0 {
                    if mask.count_ones() == 1 {
                        code = node.child[mask.trailing_zeros() as usize];
                        continue;
                    }
                    // Push the farther children, descend into the nearest.
                    let mut hits = [(0u32, 0.0f32); NODE_WIDTH];
                    let mut n = 0;
                    let mut m = mask;
                    while m != 0 {
                        let c = m.trailing_zeros() as usize;
                        m &= m - 1;
                        self.prefetch(node.child[c], payload);
                        hits[n] = (node.child[c], near[c]);
                        n += 1;
                    }
                    if ordered {
                        // Insertion sort, farthest first.
                        for i in 1..n {
                            let mut j = i;
                            while j > 0 && hits[j - 1].1 < hits[j].1 {
                                hits.swap(j - 1, j);
                                j -= 1;
                            }
                        }
                    }
                    for h in &hits[..n - 1] {
                        stack.push(*h);
                    }
                    code = hits[n - 1].0;
                    continue;
                }
            } else {
                visits[1] += 1;
                if leaf(leaf_items(code), tmax) == Visit::Stop {
                    return;
                }
            }
            // Pop the next entry that can still hold something closer.
            loop {
                match stack.pop() {
                    None => return,
                    Some((c, near)) if near <= *tmax => {
                        code = c;
                        break;
                    }
                    Some(_) => {}
                }
            }
        }
    }
}

/// Turns obvhs' binary tree into a [`Tree`]; the owner stores each leaf's
/// primitives and says where they went.
struct Collapser<'a> {
    bvh2: &'a Bvh2,
    /// Primitives under each BVH2 node.
    counts: Vec<u32>,
    /// Subtrees with at most this many primitives become leaves (<= 8).
    leaf_max: u32,
    nodes: Vec<Node>,
    depth: u32,
}

/// Stores a leaf's primitives (original indices); returns (first, count)
/// in the owner's payload array, count in 1..=8.
type LeafSink<'s> = dyn FnMut(&[u32]) -> (usize, usize) + 's;

impl<'a> Collapser<'a> {
    fn new(bvh2: &'a Bvh2, leaf_max: u32) -> Self {
        // Post-order over an explicit stack (reinsertion leaves no index
        // order to rely on, and degenerate trees can be deep).
        let n = bvh2.nodes.len();
        let mut counts = vec![0u32; n];
        let mut todo = vec![(0usize, false)];
        while let Some((i, children_done)) = todo.pop() {
            let node = &bvh2.nodes[i];
            if node.is_leaf() {
                counts[i] = node.prim_count;
            } else {
                let c = node.first_index as usize;
                if children_done {
                    counts[i] = counts[c].saturating_add(counts[c + 1]);
                } else {
                    todo.extend([(i, true), (c, false), (c + 1, false)]);
                }
            }
        }
        Self {
            bvh2,
            counts,
            leaf_max,
            nodes: vec![],
            depth: 1,
        }
    }

    fn run(mut self, sink: &mut LeafSink) -> Tree {
        let root = if self.counts[0] <= self.leaf_max {
            // Even a single leaf sits under a node, so its box is tested:
            // a TLAS of one instance must still cull the rays that miss it.
            let mut node = empty_node();
            let aabb = self.bvh2.nodes[0].aabb;
            for a in 0..3 {
                node.lo[a][0] = aabb.min[a];
                node.hi[a][0] = aabb.max[a];
            }
            node.child[0] = self.leaf(0, sink);
            self.nodes.push(node);
            0
        } else {
            self.inner(0, sink)
        };
        Tree {
            nodes: HugeArray::new(self.nodes),
            root,
            depth: self.depth,
        }
    }

    /// Makes the Node for BVH2 inner node `b` and everything under it
    /// (an explicit work list, so degenerate deep trees cannot overflow the
    /// call stack). Returns its code.
    fn inner(&mut self, b: usize, sink: &mut LeafSink) -> u32 {
        let root = self.nodes.len() as u32;
        self.nodes.push(empty_node());
        // (Node slot, BVH2 node, level)
        let mut work = vec![(root, b, 1u32)];
        while let Some((slot, b, level)) = work.pop() {
            self.depth = self.depth.max(level);
            for (k, c) in self.open(b).into_iter().enumerate() {
                let aabb = self.bvh2.nodes[c].aabb;
                let code = if self.counts[c] <= self.leaf_max {
                    self.leaf(c, sink)
                } else {
                    let child_slot = self.nodes.len() as u32;
                    self.nodes.push(empty_node());
                    work.push((child_slot, c, level + 1));
                    child_slot
                };
                let node = &mut self.nodes[slot as usize];
                for a in 0..3 {
                    node.lo[a][k] = aabb.min[a];
                    node.hi[a][k] = aabb.max[a];
                }
                node.child[k] = code;
            }
        }
        root
    }

    /// Up to eight BVH2 nodes covering inner node `b`: its two children,
    /// opened (largest surface first) while that leaves at most eight and a
    /// child is too big to be a leaf.
    fn open(&self, b: usize) -> Vec<usize> {
        let first = self.bvh2.nodes[b].first_index as usize;
        let mut children = vec![first, first + 1];
        while children.len() < NODE_WIDTH {
            let area = |n: usize| self.bvh2.nodes[n].aabb.half_area();
            let pick = children
                .iter()
                .enumerate()
                .filter(|(_, c)| self.counts[**c] > self.leaf_max)
                .max_by(|(_, a), (_, b)| area(**a).total_cmp(&area(**b)))
                .map(|(i, _)| i);
            let Some(i) = pick else { break };
            let c = children.swap_remove(i);
            let f = self.bvh2.nodes[c].first_index as usize;
            children.extend([f, f + 1]);
        }
        children
    }

    /// Hands every primitive under BVH2 node `b` to the sink; returns the leaf code.
    fn leaf(&mut self, b: usize, sink: &mut LeafSink) -> u32 {
        let mut prims = Vec::with_capacity(self.leaf_max as usize);
        let mut todo = vec![b];
        while let Some(n) = todo.pop() {
            let node = &self.bvh2.nodes[n];
            let f = node.first_index as usize;
            if node.is_leaf() {
                prims.extend_from_slice(
                    &self.bvh2.primitive_indices[f..f + node.prim_count as usize],
                );
            } else {
                todo.extend([f, f + 1]);
            }
        }
        let (first, count) = sink(&prims);
        debug_assert!((1..=8).contains(&count));
        // 2^28 leaves' worth of packets is over 10^9 triangles, far past
        // what memory holds; checked anyway rather than wrapping silently.
        assert!(
            first <= FIRST_MASK as usize,
            "BVH payload index past 2^28 (a mesh of over a billion triangles)"
        );
        LEAF | ((count as u32 - 1) << COUNT_SHIFT) | first as u32
    }
}

impl Tri4 {
    /// Packs up to four triangles; unused lanes keep zero edges (never hit).
    fn pack(prims: &[u32], tris: &[Triangle]) -> Self {
        let mut p = Tri4 {
            v0: [Vec4::ZERO; 3],
            e1: [Vec4::ZERO; 3],
            e2: [Vec4::ZERO; 3],
            prim: [u32::MAX; 4],
        };
        for (lane, &i) in prims.iter().enumerate() {
            let t = &tris[i as usize];
            let (v0, e1, e2) = (t.v0, t.v1 - t.v0, t.v2 - t.v0);
            for a in 0..3 {
                p.v0[a][lane] = v0[a];
                p.e1[a][lane] = e1[a];
                p.e2[a][lane] = e2[a];
            }
            p.prim[lane] = i;
        }
        p
    }
}

fn empty_node() -> Node {
    Node {
        lo: [[f32::INFINITY; NODE_WIDTH]; 3],
        hi: [[f32::NEG_INFINITY; NODE_WIDTH]; 3],
        child: [EMPTY; NODE_WIDTH],
    }
}

#[cfg(test)]
mod tests;
