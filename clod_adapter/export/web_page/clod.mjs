// clod-adapter's continuous level of detail on the GPU, in the PlayCanvas engine (vendored beside
// this file by `clod-export --web`). The LoD rule of clod_adapter/lod/rule.py (CLoD-GS Eq. 2 with the
// window fade, the fade ramp near s_v = 1 and the learned level gains) runs per splat and per frame
// in a work-buffer modifier (PlayCanvas's per-splat shader hook); s_v, the camera, the distance
// normaliser and the level are uniforms. Per-splat data (sigma_d, opacity logit, the gains, a
// static importance rank) are two RGBA32F extra streams filled from clod.bin.
//
// A model with merged tiers is a merge tree (clod.json's "tree", docs/lod_rule.md), drawn as one
// set: every tier's nodes are rows of one splat entity (one depth sort), and on each change
// of the level, the budget or the camera the rule of clod_tree.mjs (examples/reference_lod.py,
// ported) picks on the CPU the nodes drawn, their weight w and how each is drawn; a per-splat
// RGBA32F stream carries (w, how, the parent's row) to TREE_GLSL, which draws a lead in a hand-over
// toward its parent's row of the same splat data, shrinks and fades a sibling, fades a node that
// leaves and gives the others no footprint. A count budget (?budget=K or the panel's field) draws
// the cut at the level the rule's budgetSv picks for the view.
//
// Approximations against render_lod (docs/guide.md "In the browser"): the normaliser max d over the
// frustum and the drawn share (hence the level of the gains) are computed here on the CPU from the
// splat centres inside the frustum (every centre up to 200,000 splats, an even stride beyond),
// where render_lod counts the Gaussians whose projected footprint reaches the image.
// A tree's cut is the rule's exactly (every node, float64, for the view's exact pose); the page hands
// the engine's sort a lead's drawn centre during a hand-over (resource.centers).
import * as pc from './playcanvas.min.mjs';
import * as treeRule from './clod_tree.mjs';

const q = new URLSearchParams(location.search);
const cfg = await (await fetch('clod.json')).json();
const st = cfg.settings;
const SH_C0 = 0.28209479177387814;

// --- the rule's scalars (clod_adapter/lod/rule.py) for one model's settings ---------------------------
function rule(st) {
    const ramp = (s, r = st.fade_ramp_s_v) => Math.min(1, Math.max(Math.log(Math.max(s, 1)) / Math.log(Math.max(r, st.fade_ramp_s_v)), 0));
    const rampCap = Math.max(st.fade_ramp_s_v, Math.sqrt(Math.max(st.max_sv, 1)));     // lod.ramp_cap
    const levelMax = st.level_max ?? 1;                                                 // LodSettings.level_max
    const level = (s) => (st.max_sv > 1 ? Math.min(Math.max(Math.log(Math.max(s, 1)) / Math.log(st.max_sv), 0), levelMax) : 0);
    return {
        fadeWidthAt: (s) => st.fade_width * ramp(s),                                    // lod.fade_width_at
        fullDetailShare: (s, r) => 1 - ramp(s, r),                                      // lod.full_detail_share
        rampSv: (share1) => (share1 > 0                                                 // lod.ramp_s_v
            ? Math.min(Math.max(st.fade_ramp_s_v * Math.pow(Math.min(share1, 1), -2 / 3), st.fade_ramp_s_v), rampCap)
            : rampCap),
        levelOfFraction: (f) => (f > 0 ? level(Math.pow(Math.min(f, 1), -2 / 3)) : (st.max_sv > 1 ? levelMax : 0)),
    };
}
const logSigmoid = (x) => -Math.max(-x, 0) - Math.log1p(Math.exp(-Math.abs(x)));

const GLSL = /* glsl */ `
uniform vec3 uClodCam;
uniform float uClodInvDmax;
uniform float uClodSv;
uniform float uClodLogTauS;
uniform float uClodEps;
uniform float uClodFadeW;
uniform float uClodT;
uniform float uClodLevel;
uniform float uClodStatic;
uniform float uClodStaticRank;
uniform float uClodEq2;

// the drawn weight of a splat: lod.lod_margin and lod.fade_weight, blended over the ramp
// ((1 - t) + t fade, t = 1 - full_detail_share); "eq2" models: Eq. 2's attenuation where the mask
// keeps them; the static cut keeps ranks below a threshold
float clodWeight(vec3 center, vec4 a, vec4 b) {
    if (uClodStatic > 0.5) return b.w < uClodStaticRank ? 1.0 : 0.0;
    if (uClodT <= 0.0) return 1.0;
    float x = length(center - uClodCam) * uClodInvDmax * uClodSv;
    float sd = max(a.x, 0.0);
    float logAlpha = -max(-a.y, 0.0) - log(1.0 + exp(-abs(a.y)));
    float att = x * x / (2.0 * sd * sd + uClodEps);
    float m = logAlpha - att - uClodLogTauS;
    if (uClodEq2 > 0.5) return m > 0.0 ? exp(-att) : 0.0;
    float f = uClodFadeW > 0.0 ? clamp(m / uClodFadeW, 0.0, 1.0) : (m > 0.0 ? 1.0 : 0.0);
    return (1.0 - uClodT) + uClodT * f;
}

void modifySplatCenter(inout vec3 center) {
}

void modifySplatRotationScale(vec3 originalCenter, vec3 modifiedCenter, inout vec4 rotation, inout vec3 scale) {
    vec4 a = texelFetch(clodA, splat.uv, 0);
    vec4 b = texelFetch(clodB, splat.uv, 0);
    float lv = uClodStatic > 0.5 ? 0.0 : uClodLevel;
    float w = clodWeight(originalCenter, a, b);
    scale *= w > 0.0 ? exp(lv * a.w) : 0.0;                                 // a splat left out has no footprint
}

void modifySplatColor(vec3 center, inout vec4 color) {
    vec4 a = texelFetch(clodA, splat.uv, 0);
    vec4 b = texelFetch(clodB, splat.uv, 0);
    float lv = uClodStatic > 0.5 ? 0.0 : uClodLevel;
    color.rgb += lv * ${SH_C0} * b.xyz;                                     // sh0 gain
    color.a = clodWeight(center, a, b) / (1.0 + exp(-(a.y + lv * a.z)));  // opacity gain, fade
}
`;

// the merge tree's step 5 on the GPU (clod_tree.mjs picks per node, on the CPU): clodT = (w, how:
// clod_tree.mjs's HIDDEN, FADE, LEAD or SIBLING, the parent's row, 0). A lead in a hand-over
// (w < 1) reads its parent's row of the same splat data and is drawn with w times its own and 1 - w
// times the parent's centre, log-scales, rotation (the parent's negated when their dot product is
// negative), colour (each one's SH evaluated toward the drawn centre: SH is linear in its
// coefficients) and opacity; a sibling shrinks (scales times max(w, 1e-4)) and fades (opacity w a);
// a node that leaves fades; the others have no footprint
const TREE_GLSL = /* glsl */ `
uniform vec3 uClodCam;
const float CLOD_HIDDEN = ${treeRule.HIDDEN}.0, CLOD_FADE = ${treeRule.FADE}.0;
const float CLOD_LEAD = ${treeRule.LEAD}.0, CLOD_SIBLING = ${treeRule.SIBLING}.0;

vec4 clodNode() { return texelFetch(clodT, splat.uv, 0); }
bool clodToParent(vec4 t) { return t.y == CLOD_LEAD && t.x < 1.0; }

// the parent's centre, rotation (xyzw, as the modifier gets the splat's own) and scale
void clodParent(vec4 t, out vec3 c, out vec4 r, out vec3 s) {
    uint row = splat.index;
    setSplat(uint(t.z));
    c = getCenter();
    r = getRotation().yzwx;
    s = getScale();
    setSplat(row);
}

// the current splat's colour (its SH toward dir) and opacity
vec4 clodColor(vec3 dir) {
    vec4 c = getColor();
#if SH_BANDS > 0
    vec3 sh[SH_COEFFS];
    float scale;
    readSHData(sh, scale);
    c.rgb += evalSH(sh, dir) * scale;
#endif
    return c;
}

void modifySplatCenter(inout vec3 center) {
    vec4 t = clodNode();
    if (clodToParent(t)) {
        vec3 c, s;
        vec4 r;
        clodParent(t, c, r, s);
        center = mix(c, center, t.x);
    }
}

void modifySplatRotationScale(vec3 originalCenter, vec3 modifiedCenter, inout vec4 rotation, inout vec3 scale) {
    vec4 t = clodNode();
    if (t.y == CLOD_HIDDEN) {
        scale = vec3(0.0);
    } else if (t.y == CLOD_SIBLING) {
        scale *= max(t.x, 1e-4);
    } else if (clodToParent(t)) {
        vec3 c, s;
        vec4 r;
        clodParent(t, c, r, s);
        vec4 q = normalize(rotation), qp = normalize(r);
        rotation = normalize(mix(dot(q, qp) < 0.0 ? -qp : qp, q, t.x));
        rotation = rotation.w < 0.0 ? -rotation : rotation;  // the work buffer keeps xyz, w >= 0
        scale = exp(mix(log(s), log(scale), t.x));
    }
}

void modifySplatColor(vec3 center, inout vec4 color) {
    vec4 t = clodNode();
    if (t.y == CLOD_HIDDEN) {
        color.a = 0.0;
    } else if (t.y == CLOD_FADE || t.y == CLOD_SIBLING) {
        color.a *= t.x;
    } else if (clodToParent(t)) {
        vec3 dir = normalize(center - uClodCam);
        vec4 own = clodColor(dir);
        uint row = splat.index;
        setSplat(uint(t.z));
        vec4 par = clodColor(dir);
        setSplat(row);
        color = mix(par, own, t.x);
    }
}
`;

// --- the engine ----------------------------------------------------------------------------------
const canvas = document.getElementById('c');
const fixed = q.has('w') && q.has('h');
const device = await pc.createGraphicsDevice(canvas, { deviceTypes: ['webgl2'], antialias: false,
                                                        preserveDrawingBuffer: true });
const opts = new pc.AppOptions();
opts.graphicsDevice = device;
opts.mouse = new pc.Mouse(canvas);
opts.componentSystems = [pc.CameraComponentSystem, pc.GSplatComponentSystem];
opts.resourceHandlers = [pc.TextureHandler, pc.GSplatHandler];
const app = new pc.AppBase(canvas);
app.init(opts);
// gsplat 1.5.3's kernel in the engine's splat shaders (three of its GLSL chunks, edited by string so
// a changed engine fails here loudly): the engine draws each splat's quad out to 2 sqrt 2 sigma and
// renormalises exp(-r^2 / 2) to reach 0 at that edge; gsplat draws alpha = min(0.999, opacity
// exp(-r^2 / 2)) wherever it is >= 1/255, i.e. out to 3.33 sigma for opacity 1. So the quad is
// widened by 3.33 / 2.83 (the kernel's coordinate with it) and the plain Gaussian is drawn; the
// engine's own 1/255 discard stays.
const chunks = pc.ShaderChunks.get(device, pc.SHADERLANGUAGE_GLSL);
const edit = (name, pairs) => {
    let code = chunks.get(name);
    for (const [from, to] of pairs) {
        if (!code.includes(from)) throw new Error(`clod.mjs: the engine's ${name} chunk has changed (no "${from}")`);
        code = code.replace(from, to);
    }
    chunks.set(name, code);
};
const EXTENT = '1.1774';  // 3.33 / (2 sqrt 2)
edit('gsplatCornerVS', [
    ['float l1 = 2.0 * min(sqrt(2.0 * lambda1), vmin);', `float l1 = 2.0 * min(${EXTENT} * sqrt(2.0 * lambda1), vmin);`],
    ['float l2 = 2.0 * min(sqrt(2.0 * lambda2), vmin);', `float l2 = 2.0 * min(${EXTENT} * sqrt(2.0 * lambda2), vmin);`],
    ['corner.uv = source.cornerUV;', `corner.uv = source.cornerUV * ${EXTENT};`],
    // gsplat's low-pass filter: eps2d = 0.3 px^2 added to the projected covariance. The engine's
    // corner math runs in half pixels (its focal length is viewport_size * projMat00 = 2 f, its quad
    // offsets are scaled by 1 / width for NDC), so its "+ 0.3" is 0.075 px^2: a quarter of gsplat's
    // filter, which left every thin splat narrower and sharper than render_lod draws it (the page's
    // s_v = 1 frames on fern were 26.1-26.3 dB from render_lod's, the differences along every edge;
    // 35.7-35.9 dB with this: benchmarks/studies/web_viewer.py) and made its footprint follow the level's
    // scale gain several times more steeply (popping 9.2x -> 11.1x on fern). 4 x 0.3 in those units
    // is gsplat's 0.3 px^2.
    ['float diagonal1 = cov[0][0] + 0.3;', 'float diagonal1 = cov[0][0] + 1.2;'],
    ['float diagonal2 = cov[1][1] + 0.3;', 'float diagonal2 = cov[1][1] + 1.2;'],
    // no cap on a splat's extent: the engine caps each axis of the quad at the viewport's smaller
    // side (at most 1024), which squeezes a splat larger than the screen into it, so its falloff
    // lands on the screen instead of its flat middle. gsplat has no cap (the rasteriser clips to
    // the image): skull's model holds a dim, dark Gaussian some 30 units across around the scene,
    // which darkens every frame of render_lod by ~8 % and the capped page only in a blob; its
    // s_v = 1 frames were 28.8 dB from render_lod's in test view 49 (benchmarks/studies/web_viewer.py)
    ['float vmin = min(1024.0, min(viewport_size.x, viewport_size.y));', 'float vmin = 1e6;'],
    // ... and gsplat's Jacobian: x/z and y/z clamped to 1.3 x the half field of view (tan = 1 /
    // projMat; the principal point taken as centred), so a splat beside the image does not smear
    // across it; without the cap above the engine's unclamped form drew one thin splat of skull's
    // beside test view 09 over the whole frame
    ['vec2 J2 = -J1 / vp.z * vp.xy;',
     'vec2 clodLim = 1.3 / abs(vec2(center.projMat00, center.projMat11));\n\tvec2 J2 = -J1 * clamp(vp.xy / vp.z, -clodLim, clodLim);'],
]);
// the engine's opacity-aware quad (each splat's quad clipped to where opacity exp(-r^2 / 2) falls to
// 1/255, gsplat's extent), measured against the widened quad: no splat's quad grows beyond that
edit('gsplatCommonVS', [
    ['float clip = min(1.0, sqrt(max(0.0, log(alpha / alphaClipValue))) * 0.5);',
     `float clip = min(1.0, sqrt(max(0.0, log(alpha / alphaClipValue))) * ${(0.5 / 1.1774).toFixed(6)});`],
]);
edit('gsplatPS', [
    ['if (A > 1.0) {\n\t\tdiscard;\n\t}', ''],
    ['mediump float alpha = normExp(A) * gaussianColor.a;', 'float alpha = min(0.999, exp(-4.0 * A) * gaussianColor.a);'],
    ['mediump float A = dot(gaussianUV, gaussianUV);', 'float A = dot(gaussianUV, gaussianUV);'],
]);
// the work buffer in half floats: the engine's default "compact" layout stores each splat's opacity
// in 8 bits, its log-scale in 8 bits (8.6 % steps) and its colour in 11/11/10 bits, so the level
// gains' continuous drift reached the frames as per-splat jumps; "large" keeps colour, opacity and
// scale as half floats (benchmarks/studies/web_popping_steps.py; docs/guide.md "In the browser")
app.scene.gsplat.dataFormat = pc.GSPLATDATA_LARGE;
// no size culling: render_lod draws every splat whose footprint reaches the image (the engine drops
// splats whose quad is under 2 px by default, and the level's scale gains move splats across it)
app.scene.gsplat.minPixelSize = 0;
if (fixed) {
    app.setCanvasFillMode(pc.FILLMODE_NONE);
    app.setCanvasResolution(pc.RESOLUTION_FIXED, +q.get('w'), +q.get('h'));
} else {
    app.setCanvasFillMode(pc.FILLMODE_FILL_WINDOW);
    app.setCanvasResolution(pc.RESOLUTION_AUTO);
    window.addEventListener('resize', () => app.resizeCanvas());
}

// --- the model: the adapted model, or a merge tree (cfg.tree) ---------------------------------------
// reorder: false keeps the file's order (the engine sorts a .ply along a Morton curve by default),
// so splat i of the resource is row i of its .bin; a unified gsplat entity.
async function loadAsset(name, url) {
    const asset = new pc.Asset(name, 'gsplat', { url }, { reorder: false });
    app.assets.add(asset);
    await new Promise((resolve, reject) => {
        asset.ready(resolve);
        asset.on('error', reject);
        app.assets.load(asset);
    });
    return asset;
}
function addEntity(name, asset, glsl) {
    const entity = new pc.Entity(name);
    entity.addComponent('gsplat', { asset, unified: true });
    app.root.addChild(entity);
    entity.gsplat.setWorkBufferModifier({ glsl });
    entity.gsplat.workBufferUpdate = pc.WORKBUFFER_UPDATE_ALWAYS;
    return entity;
}
async function loadModel(name, spec, st) {
    const N = spec.count;
    const raw = new Float32Array(await (await fetch(spec.data)).arrayBuffer());
    const col = Object.fromEntries(cfg.streams.map((k, i) => [k, raw.subarray(i * N, (i + 1) * N)]));
    const asset = await loadAsset(name, spec.model);
    const resource = asset.resource;
    resource.format.addExtraStreams([{ name: 'clodA', format: pc.PIXELFORMAT_RGBA32F },
                                     { name: 'clodB', format: pc.PIXELFORMAT_RGBA32F }]);
    const fill = (tname, cols) => {
        const tex = resource.getTexture(tname);
        const data = tex.lock();
        for (let i = 0; i < N; i++) {
            for (let c = 0; c < 4; c++) data[4 * i + c] = cols[c][i];
        }
        tex.unlock();
    };
    const zeros = new Float32Array(N);
    fill('clodA', [col.sigma_d, col.opacity_logit, col.opacity_gain || zeros, col.scale_gain || zeros]);
    fill('clodB', [col.f_dc_gain_0 || zeros, col.f_dc_gain_1 || zeros, col.f_dc_gain_2 || zeros, col.static_rank]);
    const entity = addEntity(name, asset, GLSL);
    return { N, col, st, r: rule(st), entity, stride: Math.max(1, Math.ceil(N / 200000)), ranks: new Float32Array(N),
             drawn: 0, inFrustum: 0, level: 0, dmax: 0, ramp: st.fade_ramp_s_v };
}
// a merge tree: every tier's nodes in one entity (the rows of model.ply and clod.bin), the rule's
// choice per node in the stream clodT (its third channel the parent's row, set once here)
async function loadTree() {
    const raw = new Float32Array(await (await fetch(cfg.data)).arrayBuffer());
    const tr = treeRule.readTree(cfg.tree, cfg.streams, raw);
    const asset = await loadAsset('tree', cfg.model);
    asset.resource.format.addExtraStreams([{ name: 'clodT', format: pc.PIXELFORMAT_RGBA32F }]);
    const tex = asset.resource.getTexture('clodT');
    const data = tex.lock();
    for (let i = 0; i < tr.N; i++) data[4 * i + 2] = tr.parent[i];
    tex.unlock();
    return { tr, tex, resource: asset.resource, entity: addEntity('tree', asset, TREE_GLSL),
             out: { w: new Float32Array(tr.N), kind: new Uint8Array(tr.N) }, moved: new Uint8Array(tr.N) };
}
const tree = cfg.tree ? await loadTree() : null;
const model = tree ? null : await loadModel('model', cfg, st);
const N = tree ? cfg.tree.counts[0] : model.N;

const camera = new pc.Entity('camera');
camera.addComponent('camera', { clearColor: new pc.Color(0, 0, 0, 1), nearClip: 0.01, farClip: 1e4 });
app.root.addChild(camera);

// ?blend=16: blending in half floats. The camera draws into an RGBA16F target, copied once per frame
// to the canvas, instead of straight into the 8-bit canvas, where each of a pixel's ~50 blends is
// rounded to 1/255 (the s_v = 1 frame against render_lod: 44.4 dB on fern's first view against 35.7
// in the canvas; popping 11.8x against 11.1x; benchmarks/studies/web_viewer.py). The camera keeps its sRGB
// output, so the splats blend in gamma space as render_lod does (the engine's CameraFrame blends in
// linear light). Off by default: SwiftShader's frame took 20-60 % longer with it on fern and skull
// (docs/guide.md "In the browser").
const blendFormat = q.get('blend') === '16'
    ? device.getRenderableHdrFormat([pc.PIXELFORMAT_RGBA16F], false, 1, true) : undefined;
let target = null;
function makeTarget() {
    if (blendFormat === undefined) return;
    const W = canvas.width, H = canvas.height;
    if (target && target.width === W && target.height === H) return;
    target?.destroyTextureBuffers();
    target?.destroy();
    const tex = new pc.Texture(device, { name: 'clodBlend', width: W, height: H, format: blendFormat, mipmaps: false,
                                         minFilter: pc.FILTER_NEAREST, magFilter: pc.FILTER_NEAREST,
                                         addressU: pc.ADDRESS_CLAMP_TO_EDGE, addressV: pc.ADDRESS_CLAMP_TO_EDGE });
    target = new pc.RenderTarget({ name: 'clodBlend', colorBuffer: tex, depth: true });
    camera.camera.renderTarget = target;
}
const copyShader = pc.ShaderUtils.createShader(device, {
    uniqueName: 'clodCopy', attributes: { vertex_position: pc.SEMANTIC_POSITION }, vertexChunk: 'fullscreenQuadVS',
    fragmentGLSL: 'uniform sampler2D clodSource;\n' +
        'void main(void) { gl_FragColor = vec4(texelFetch(clodSource, ivec2(gl_FragCoord.xy), 0).rgb, 1.0); }',
});
const sourceId = device.scope.resolve('clodSource');
makeTarget();
device.on('resizecanvas', makeTarget);
app.on('postrender', () => {
    if (!target) return;
    device.setBlendState(pc.BlendState.NOBLEND);
    device.setDepthState(pc.DepthState.NODEPTH);
    device.setCullMode(pc.CULLFACE_NONE);
    sourceId.setValue(target.colorBuffer);
    pc.drawQuadWithShader(device, null, copyShader);
});

// --- state: s_v, the static toggle, the camera ----------------------------------------------------
// drawn, inFrustum, level, dmax, ramp: the model's Gaussians. A merge tree:
// sv the level drawn (the budget's), budget the count budget or null, drawn the drawn nodes with
// their centre in the frustum (what a budget counts), inFrustum tier 0's centres there, and tree:
// {drawn, inView} per tier (every drawn node; those in the frustum) and handOver (the leads and
// siblings drawn with 0 < w < 1)
const state = { sv: 1, static: false, cam: 0, drawn: 0, inFrustum: 0, level: 0, dmax: 0, ramp: 1.1, frameMs: NaN, updates: 0,
                budget: null, tree: null };
const inv = new pc.Mat4();
const p = new pc.Vec3();

// the pinhole K of a camera (fx, fy, cx, cy in pixels) when the canvas has its size, else one focal
// length from the vertical field of view and a centred principal point (a resized window)
function intrinsics() {
    const c = cfg.cameras[state.cam], W = canvas.width, H = canvas.height;
    if (W === c.width && H === c.height) return c.K;
    const f = 0.5 * H / Math.tan(0.5 * c.fov * Math.PI / 180);
    return [f, f, 0.5 * W, 0.5 * H];
}

// OpenGL projection of a pinhole K (x right, y up, looking down -z; clip depth near..far)
function pinholeProjection(mat) {
    const [fx, fy, cx, cy] = intrinsics(), W = canvas.width, H = canvas.height;
    const n = camera.camera.nearClip, f = camera.camera.farClip;
    mat.set([2 * fx / W, 0, 0, 0, 0, 2 * fy / H, 0, 0, 1 - 2 * cx / W, 2 * cy / H - 1, -(f + n) / (f - n), -1,
             0, 0, -2 * f * n / (f - n), 0]);
}

function setCamera(i) {
    state.cam = (i + cfg.cameras.length) % cfg.cameras.length;
    const c = cfg.cameras[state.cam];
    camera.setPosition(...c.position);
    camera.setRotation(new pc.Quat(...c.rotation));
    camera.camera.fov = c.fov;
    camera.camera.calculateProjection = pinholeProjection;
    document.getElementById('camname').textContent = c.name;
    update();
}

// the model at s: the frustum (lod.in_frustum), the normaliser, the drawn count, the level and the
// uniforms of its modifier
function updateModel(m, s, isStatic) {
    const { N, col, st, r, stride, ranks } = m;
    const W = canvas.width, H = canvas.height;
    const [fx, fy, cx, cy] = intrinsics();
    const cp = camera.getPosition();
    const logTauS = Math.log(st.tau * s);
    const inside = new Uint8Array(N);
    let dmax = 0, nIn = 0;
    for (let i = 0; i < N; i += stride) {
        p.set(col.x[i], col.y[i], col.z[i]);
        inv.transformPoint(p, p);
        const z = -p.z;  // OpenGL view space looks down -z
        if (!(z > 0.01)) continue;
        const u = fx * p.x / z + cx, v = -fy * p.y / z + cy;
        if (u >= 0 && u < W && v >= 0 && v < H) {
            inside[i] = 1;
            nIn++;
            const dx = col.x[i] - cp.x, dy = col.y[i] - cp.y, dz = col.z[i] - cp.z;
            dmax = Math.max(dmax, Math.sqrt(dx * dx + dy * dy + dz * dz));
        }
    }
    // drawn: Eq. 2's mask at s (everything in view at s = 1); kept1: the mask at s_v = 1 (the ramp)
    let drawn = 0, kept1 = 0;
    const eq2 = st.fade === 'eq2';
    const invD = 1 / Math.max(dmax, 1e-12);
    const logTau = Math.log(st.tau);
    for (let i = 0; i < N; i += stride) {
        if (!inside[i]) continue;
        const dx = col.x[i] - cp.x, dy = col.y[i] - cp.y, dz = col.z[i] - cp.z;
        const x1 = Math.sqrt(dx * dx + dy * dy + dz * dz) * invD, x = x1 * s;
        const sd = Math.max(col.sigma_d[i], 0);
        const la = logSigmoid(col.opacity_logit[i]), den = 2 * sd * sd + st.eps;
        if (la - x1 * x1 / den - logTau > 0) kept1++;
        if ((s <= 1 && !eq2) || la - x * x / den - logTauS > 0) drawn++;
    }
    m.ramp = nIn ? r.rampSv(kept1 / nIn) : st.fade_ramp_s_v;
    const t = eq2 ? 1 : 1 - r.fullDetailShare(s, m.ramp);
    const share = nIn ? drawn / nIn : 1;
    m.level = s <= 1 || eq2 ? 0 : t * r.levelOfFraction(share);
    // what is drawn with a footprint: within the ramp (t < 1) every splat in view, at weight
    // (1 - t) + t fade, as render_lod's n_rendered; the static cut and the level take the mask's count
    m.drawn = Math.round((!eq2 && t < 1 ? nIn : drawn) * stride);
    m.inFrustum = Math.round(nIn * stride);
    m.dmax = dmax;
    // the static cut: the same count in view, by importance rank
    let staticRank = Infinity;
    if (isStatic) {
        let k = 0;
        for (let i = 0; i < N; i += stride) if (inside[i]) ranks[k++] = col.static_rank[i];
        const sorted = ranks.subarray(0, k).sort();
        staticRank = drawn >= k ? Infinity : (drawn > 0 ? sorted[drawn - 1] + 0.5 : -1);
    }
    const g = m.entity.gsplat;
    g.setParameter('uClodCam', [cp.x, cp.y, cp.z]);
    g.setParameter('uClodInvDmax', invD);
    g.setParameter('uClodSv', s);
    g.setParameter('uClodLogTauS', logTauS);
    g.setParameter('uClodEps', Math.max(st.eps, 1e-20));
    g.setParameter('uClodFadeW', r.fadeWidthAt(s));
    g.setParameter('uClodT', s <= 1 && !eq2 ? 0 : t);
    g.setParameter('uClodEq2', eq2 ? 1 : 0);
    g.setParameter('uClodLevel', m.level);
    g.setParameter('uClodStatic', isStatic ? 1 : 0);
    g.setParameter('uClodStaticRank', Math.min(staticRank, 3.0e38));
}

// the frame's level (or the static cut of the same count)
function updatePlain() {
    updateModel(model, state.sv, state.static);
    Object.assign(state, { drawn: model.drawn, inFrustum: model.inFrustum, level: model.level, dmax: model.dmax,
                           ramp: model.ramp });
}

// the merge tree's cut for the view (its exact pose, the projection's K) at s_v or within the
// budget (clod_tree.mjs), each node's weight and kind uploaded to clodT
function updateTree() {
    const { tr, tex, out, entity, resource, moved } = tree;
    const cam = { viewmat: cfg.cameras[state.cam].viewmat, K: intrinsics(), width: canvas.width, height: canvas.height };
    const tt = treeRule.terms(tr, cam, state.budget !== null);
    const r = treeRule.draw(tr, cam, state.sv, state.budget, out, tt);
    const data = tex.lock();
    for (let i = 0; i < tr.N; i++) {
        data[4 * i] = out.w[i];
        data[4 * i + 1] = out.kind[i];
    }
    tex.unlock();
    // the centres the engine sorts by: a lead in a hand-over where TREE_GLSL draws it
    const cs = resource.centers;
    let changed = false;
    for (let i = 0; i < tr.N; i++) {
        const m = out.kind[i] === treeRule.LEAD && out.w[i] < 1;
        if (!m && !moved[i]) continue;
        const w = m ? out.w[i] : 1, p = tr.parent[i];
        cs[3 * i] = w * tr.x[i] + (1 - w) * tr.x[p];
        cs[3 * i + 1] = w * tr.y[i] + (1 - w) * tr.y[p];
        cs[3 * i + 2] = w * tr.z[i] + (1 - w) * tr.z[p];
        moved[i] = m ? 1 : 0;
        changed = true;
    }
    if (changed) resource.centersVersion++;
    const cp = camera.getPosition();
    entity.gsplat.setParameter('uClodCam', [cp.x, cp.y, cp.z]);
    let inFrustum = 0;
    for (let i = 0; i < tr.n[0]; i++) inFrustum += tt.frustum[i];
    Object.assign(state, { sv: r.s_v, drawn: r.inView.reduce((a, b) => a + b, 0), inFrustum,
                           tree: { drawn: r.drawn, inView: r.inView, handOver: r.handOver } });
    if (state.budget !== null) slider.value = sliderOf(state.sv);
    document.getElementById('ttiers').textContent = r.drawn.map((x) => x.toLocaleString()).join(' / ');
    document.getElementById('thand').textContent = r.handOver.toLocaleString();
}

function update() {
    inv.copy(camera.getWorldTransform()).invert();
    if (tree) updateTree();
    else updatePlain();
    const s = state.sv;
    state.updates++;
    document.getElementById('svv').textContent = s.toFixed(2) + (state.budget !== null ? ' (the budget\'s)' : '');
    document.getElementById('share').textContent = `${(100 * Math.pow(s, -1.5)).toFixed(1)} %`;
    document.getElementById('drawn').textContent = state.drawn.toLocaleString();
    document.getElementById('infrustum').textContent = state.inFrustum.toLocaleString();
    document.getElementById('total').textContent = N.toLocaleString();
}

// --- the page: slider, toggle, cameras, frame time -------------------------------------------------
const slider = document.getElementById('sv');
// log scale from 1 to 1.2 max_sv; a merge tree's to clod.json's tree.sv_max (1.2 times the last
// tier's max_sv at the model's s_v)
const svMax = tree ? cfg.tree.sv_max : st.max_sv * 1.2;
const svOfSlider = (v) => Math.exp(Math.log(svMax) * v / 1000);
const sliderOf = (s) => Math.round(1000 * Math.log(s) / Math.log(svMax));
// a merge tree: the budget field instead of the static cut (a count of drawn nodes in view; empty: off)
const budgetField = document.getElementById('budget');
const budgetOf = (k) => (tree && k !== null && k !== '' && Number.isFinite(+k) ? Math.max(0, Math.floor(+k)) : null);
if (tree) {
    document.getElementById('budgetrow').hidden = false;
    document.getElementById('staticrow').hidden = true;
    document.getElementById('treeinfo').hidden = false;
    document.getElementById('tnodes').textContent = tree.tr.N.toLocaleString();
}
function setBudget(k) {
    state.budget = budgetOf(k);
    budgetField.value = state.budget ?? '';
    update();
}
budgetField.addEventListener('change', () => setBudget(budgetField.value));
slider.addEventListener('input', () => {
    state.budget = null;
    budgetField.value = '';
    state.sv = svOfSlider(+slider.value);
    update();
});
document.getElementById('static').addEventListener('change', (e) => { state.static = e.target.checked; update(); });
document.getElementById('prev').addEventListener('click', () => setCamera(state.cam - 1));
document.getElementById('next').addEventListener('click', () => setCamera(state.cam + 1));
const times = [];
let last = performance.now();
app.on('frameend', () => {
    const now = performance.now();
    times.push(now - last);
    last = now;
    if (times.length > 30) times.shift();
    const sorted = [...times].sort((a, b) => a - b);
    state.frameMs = sorted[Math.floor(sorted.length / 2)];
    document.getElementById('ms').textContent = state.frameMs.toFixed(1);
});
app.start();
// ?s_v=X, ?budget=K (a merge tree), ?cam=i
if (q.has('s_v')) {
    state.sv = Math.max(1, +q.get('s_v') || 1);
    slider.value = sliderOf(state.sv);
}
state.budget = budgetOf(q.get('budget'));
budgetField.value = state.budget ?? '';
setCamera(+(q.get('cam') || 0));

// the page's API (tests, scripts): set the level or the toggle, read what is drawn
window.clod = {
    state,
    setSv(s) {
        state.sv = Math.max(1, +s);
        state.budget = null;
        budgetField.value = '';
        slider.value = sliderOf(state.sv);
        update();
    },
    setBudget,  // a merge tree: draw within k drawn nodes in view (null: the slider's level again)
    setStatic(on) { state.static = !!on; document.getElementById('static').checked = state.static; update(); },
    setCamera,
    svMax,  // the slider's top
    frames: () => app.frame,
    // the engine settings the rule's fidelity depends on (the work buffer's precision, size culling)
    engine: () => ({ dataFormat: app.scene.gsplat.dataFormat, minPixelSize: app.scene.gsplat.minPixelSize,
                     blendFormat: target ? target.colorBuffer.format : null, halfFloatBlend: target?.colorBuffer.format === pc.PIXELFORMAT_RGBA16F }),
};
window.__clodReady = true;
