// The merge tree's drawing rule (docs/lod_rule.md) for the page of a `clod-adapt`
// model: examples/reference_lod.py ported step by step (frustum, terms, budgetSv, leads, draw keep
// its names, steps and order, so a change to the rule is mirrored here line by line). Float64
// arithmetic over typed arrays; the nodes of all tiers are one array, tier 0's rows first (tier k
// is rows off[k] .. off[k] + n[k] - 1) and a node's parent is its row in that array. No engine and
// no DOM: clod.mjs draws with it, tests/test_web_tree.py runs it in node against the reference.
//
// What runs here per camera is steps 1-4 and 6 and step 5's choice per node: whether it is drawn,
// its weight w and how (KIND); the attributes themselves are interpolated on the GPU by clod.mjs's
// work-buffer modifier (TREE_GLSL), which reads the parent's row of the same splat data.

export const F = 1.25;  // the hand-over's width in s_v
export const M = 1.6;  // a hand-over or an exit lasts over the last min(M, U / max(E, 1)) of a node's interval
// how a node is drawn (draw's out.kind): not at all, as it is with its opacity times w (it
// leaves, or the last tier fades), the lead growing into its parent, a sibling shrinking and fading
export const HIDDEN = 0, FADE = 1, LEAD = 2, SIBLING = 3;

// the tree from clod.json's "tree" and clod.bin's streams (web.py TREE_STREAMS, [N] float32 each)
export function readTree(spec, streams, raw) {
    const N = spec.counts.reduce((a, b) => a + b, 0);
    const col = Object.fromEntries(streams.map((k, i) => [k, raw.subarray(i * N, (i + 1) * N)]));
    const off = [];
    spec.counts.reduce((a, n) => (off.push(a), a + n), 0);
    const opacity = new Float64Array(N);
    for (let i = 0; i < N; i++) opacity[i] = 1 / (1 + Math.exp(-col.opacity_logit[i]));
    const tr = { N, T: spec.counts.length - 1, n: spec.counts, off, x: col.x, y: col.y, z: col.z,
                 sigmaD: col.sigma_d, exit: col.exit, dRef: col.d_ref, parent: Int32Array.from(col.parent), opacity,
                 logScales: [col.scale_0, col.scale_1, col.scale_2] };
    tr.lead = leads(tr);
    return tr;
}

// [N] 1 where the centre is in front (z > 0.01) and projects inside the image. cam: viewmat [16]
// row-major world-to-camera (OpenCV axes), K [fx, fy, cx, cy] pixels, width, height
export function frustum(tr, cam) {
    const v = cam.viewmat, [fx, fy, cx, cy] = cam.K, W = cam.width, H = cam.height;
    const out = new Uint8Array(tr.N);
    for (let i = 0; i < tr.N; i++) {
        const mx = tr.x[i], my = tr.y[i], mz = tr.z[i];
        const x = mx * v[0] + my * v[1] + mz * v[2] + v[3];
        const y = mx * v[4] + my * v[5] + mz * v[6] + v[7];
        const z = mx * v[8] + my * v[9] + mz * v[10] + v[11];
        const ax = fx * x + cx * z, ay = fy * y + cy * z;
        out[i] = z > 0.01 && ax >= 0 && ax < W * z && ay >= 0 && ay < H * z ? 1 : 0;
    }
    return out;
}

// steps 1-3 for one camera: per node the entry E, the end U and whether it fades (and the frustum);
// with ref, step 6's: every node's d' its d_ref
export function terms(tr, cam, ref = false) {
    const { N, T, n, off, parent } = tr, v = cam.viewmat;
    const c = [0, 1, 2].map((j) => -(v[j] * v[3] + v[4 + j] * v[7] + v[8 + j] * v[11]));  // -R^T t
    const d = new Float64Array(N);
    for (let i = 0; i < N; i++) {
        const dx = tr.x[i] - c[0], dy = tr.y[i] - c[1], dz = tr.z[i] - c[2];
        d[i] = ref ? tr.dRef[i] : Math.sqrt(dx * dx + dy * dy + dz * dz);
    }
    const fr = frustum(tr, cam);
    let D = 0, any = false;
    for (let i = off[T]; i < N; i++) if (fr[i]) { any = true; D = Math.max(D, d[i]); }
    if (!any) for (let i = off[T]; i < N; i++) D = Math.max(D, d[i]);
    D = ref ? 1.0 : Math.max(D, 1e-12);
    for (let i = 0; i < N; i++) d[i] = Math.max(d[i] / D, 1e-12);
    const E = new Float64Array(N);  // tier 0 enters at 0
    for (let k = T; k > 0; k--) {
        for (let i = off[k]; i < off[k] + n[k]; i++) {
            let e = tr.sigmaD[i] / d[i];
            if (k < T) e = Math.min(e, E[parent[i]] / F);
            E[i] = Math.max(e, F ** k);
        }
    }
    const U = new Float64Array(N), fade = new Uint8Array(N);
    for (let k = 0; k <= T; k++) {
        for (let i = off[k]; i < off[k] + n[k]; i++) {
            const X = Math.max(tr.exit[i] / d[i], F * Math.max(E[i], 1.0));
            if (k === T) {
                U[i] = X;
                fade[i] = 1;
            } else {
                const f = X < E[parent[i]];  // a lead's exit is +inf: it hands over
                U[i] = f ? X : E[parent[i]];
                fade[i] = f ? 1 : 0;
            }
        }
    }
    return { E, U, fade, frustum: fr };
}

// step 6: the smallest s_v >= 1 from which no cut holds more than k centres in the frustum. Each
// node in the frustum is drawn on [max(E, 1), U); the count on [uniq[j], uniq[j + 1]) is the
// intervals begun at or before uniq[j] less those ended there (the reference's cumsum), from the
// two sorted ends
export function budgetSv(tr, tt, k) {
    const { E, U, frustum: fr } = tt;
    let lo = new Float64Array(tr.N), hi = new Float64Array(tr.N), m = 0;
    for (let i = 0; i < tr.N; i++) {
        const a = Math.max(E[i], 1.0);
        if (fr[i] && U[i] > a) { lo[m] = a; hi[m] = U[i]; m++; }
    }
    lo = lo.subarray(0, m).sort();
    hi = hi.subarray(0, m).sort();
    const uniq = new Float64Array(2 * m + 1), count = new Float64Array(2 * m + 1);
    let a = 0, b = 0, j = 0, one = true;
    while (a < m || b < m || one) {
        const u = Math.min(a < m ? lo[a] : Infinity, b < m ? hi[b] : Infinity, one ? 1.0 : Infinity);
        if (u === 1.0) one = false;
        while (a < m && lo[a] === u) a++;
        while (b < m && hi[b] === u) b++;
        uniq[j] = u;
        count[j++] = a - b;
    }
    // the first uniq from which the count never exceeds k (suffix max), else the coarsest end
    let first = j - 1;
    for (let top = -Infinity, i = j - 1; i >= 0; i--) {
        top = Math.max(top, count[i]);
        if (top > k) break;
        first = i;
    }
    return uniq[first];
}

// step 3's lead child of each parent: the one whose exit is +inf ([N] 1/0; the last tier 0)
export function leads(tr) {
    const out = new Uint8Array(tr.N);
    for (let i = 0; i < tr.off[tr.T]; i++) out[i] = tr.exit[i] === Infinity ? 1 : 0;
    return out;
}

// what one camera draws (steps 1-6) at s_v, or within a budget of k centres in the frustum when
// budget is a number: fills out.w [N] (the weight, 1 = the node's own attributes; 0 where not
// drawn) and out.kind [N] (HIDDEN, FADE, LEAD, SIBLING) and returns { s_v, drawn, inView,
// handOver } (drawn and inView per tier: the drawn nodes, those with their centre in the frustum;
// handOver: the leads and siblings drawn with w < 1). tt: terms(tr, cam, budget is a number), when
// already at hand
export function draw(tr, cam, sv, budget = null, out = { w: new Float32Array(tr.N), kind: new Uint8Array(tr.N) },
                     tt = terms(tr, cam, budget !== null && budget !== undefined)) {
    const { E: ns, U: ups, fade: fades, frustum: fr } = tt, { w: ws, kind: kinds } = out, lead = tr.lead;
    const s = budget !== null && budget !== undefined ? budgetSv(tr, tt, budget) : Math.max(+sv, 1.0);
    const drawn = [], inView = [];
    let handOver = 0;
    for (let k = 0; k <= tr.T; k++) {
        let nd = 0, nv = 0;
        for (let i = tr.off[k], end = tr.off[k] + tr.n[k]; i < end; i++) {
            if (!(ns[i] <= s && s < ups[i])) {
                ws[i] = 0;
                kinds[i] = HIDDEN;
                continue;
            }
            const width = Math.min(M, ups[i] / Math.max(ns[i], 1.0));
            const w = Math.min(Math.max(Math.log(ups[i] / s) / Math.log(width), 0), 1);
            // a row fading out keeps its attributes; the lead grows into its parent; its siblings
            // shrink and fade where they are
            const kind = fades[i] ? FADE : lead[i] ? LEAD : SIBLING;
            ws[i] = w;
            kinds[i] = kind;
            nd++;
            nv += fr[i];
            if (kind !== FADE && w < 1) handOver++;
        }
        drawn.push(nd);
        inView.push(nv);
    }
    return { s_v: s, drawn, inView, handOver, out };
}
