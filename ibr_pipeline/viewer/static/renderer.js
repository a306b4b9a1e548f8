// The two-layer IBR renderer of Xu et al. 2021 §5.1 in WebGL2: render/ibr.py's IBRModel.render,
// pass for pass. Per layer over the selected views: smallest IBR cost (COST), front-most depth
// among points within the cost margin (FRONT), fuzzy-depth-tested Eq. 15 blend x texture alpha
// (BLEND) -- the GLSL of render/shaders, rewritten for WebGL2 by viewer/bundle.py -- or, with
// visibility per_view, each view z-buffered alone (SINGLE) and added (post.ACCUM). Then
// normalisation, push-pull hole filling and the Eq. 3 composition I0 + beta I1 (post.js).
import { camFromWorld4, fromManifest, glMat, projection, sourceMatrix } from "./camera.js";
import * as post from "./post.js";
import { chooseViews } from "./selection.js";

const LAYERS = ["single", "surface", "reflection"];
export const MODES = { composite: 0, surface: 1, reflection: 2, single: 3 };

function compile(gl, vs, fs, name) {
  const prog = gl.createProgram();
  for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
    const sh = gl.createShader(type);
    gl.shaderSource(sh, src);
    gl.compileShader(sh);
    if (!gl.getShaderParameter(sh, gl.COMPILE_STATUS)) {
      throw new Error(`shader ${name}: ${gl.getShaderInfoLog(sh)}`);
    }
    gl.attachShader(prog, sh);
  }
  gl.bindAttribLocation(prog, 0, "in_pos");
  gl.bindAttribLocation(prog, 1, "in_color");
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) {
    throw new Error(`program ${name}: ${gl.getProgramInfoLog(prog)}`);
  }
  const uni = {};
  const n = gl.getProgramParameter(prog, gl.ACTIVE_UNIFORMS);
  for (let i = 0; i < n; i++) {
    const u = gl.getActiveUniform(prog, i);
    uni[u.name] = gl.getUniformLocation(prog, u.name);
  }
  return { prog, uni };
}

function setUniforms(gl, p, values) {
  for (const [k, v] of Object.entries(values)) {
    const loc = p.uni[k];
    if (loc === undefined) continue;  // optimised away or not in this pass
    if (v instanceof Float32Array && v.length === 16) gl.uniformMatrix4fv(loc, false, v);
    else if (Array.isArray(v) && v.length === 3) gl.uniform3f(loc, v[0], v[1], v[2]);
    else if (Array.isArray(v) && v.length === 2) gl.uniform2f(loc, v[0], v[1]);
    else if (typeof v === "boolean") gl.uniform1i(loc, v ? 1 : 0);
    else if (v && v.int !== undefined) gl.uniform1i(loc, v.int);
    else gl.uniform1f(loc, v);
  }
}

export class IBRRenderer {
  constructor(gl, manifest, base) {
    for (const ext of ["EXT_color_buffer_float", "EXT_float_blend"]) {
      if (!gl.getExtension(ext)) throw new Error(`this browser's WebGL2 lacks ${ext} (float render targets)`);
    }
    this.gl = gl;
    this.m = manifest;
    this.base = base;
    this.s = manifest.settings;
    this.views = manifest.views.map((v) => ({ ...v, cam: fromManifest(v) }));
    this.gpu = new Map();      // "k/layer" -> {vao, count, rgb, aux, hasBeta}
    this.loading = new Map();  // "k/layer" -> Promise
    this.targets = null;
    this.emptyVao = gl.createVertexArray();
    const sh = manifest.shaders;
    this.p = {
      cost: compile(gl, sh.VERTEX, sh.COST, "COST"),
      front: compile(gl, sh.VERTEX, sh.FRONT, "FRONT"),
      blend: compile(gl, sh.VERTEX, sh.BLEND, "BLEND"),
      single: compile(gl, sh.VERTEX, sh.SINGLE, "SINGLE"),
      accum: compile(gl, post.FULLSCREEN, post.ACCUM, "ACCUM"),
      normalize: compile(gl, post.FULLSCREEN, post.NORMALIZE, "NORMALIZE"),
      down: compile(gl, post.FULLSCREEN, post.DOWN, "DOWN"),
      up: compile(gl, post.FULLSCREEN, post.UP, "UP"),
      fill: compile(gl, post.FULLSCREEN, post.FILL, "FILL"),
      compose: compile(gl, post.FULLSCREEN, post.COMPOSE, "COMPOSE"),
    };
    this.bytes = 0;
  }

  // --- loading: meshes and textures of (view, layer), on demand ---------------------------------
  layerSpec(k, layer) { return this.views[k].layers[layer]; }

  async _fetch(file) {
    const r = await fetch(this.base + file);
    if (!r.ok) throw new Error(`${file}: HTTP ${r.status} (rerun \`ibr view --rebuild\`)`);
    return r;
  }

  async _texture(file, srgb) {
    const gl = this.gl;
    const blob = await (await this._fetch(file)).blob();
    const img = await createImageBitmap(blob, { premultiplyAlpha: "none", colorSpaceConversion: "none" });
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);  // image row 0 = texture row 0, as offline
    gl.pixelStorei(gl.UNPACK_PREMULTIPLY_ALPHA_WEBGL, false);
    gl.pixelStorei(gl.UNPACK_COLORSPACE_CONVERSION_WEBGL, gl.NONE);
    gl.texImage2D(gl.TEXTURE_2D, 0, srgb ? gl.SRGB8_ALPHA8 : gl.RGBA8, img.width, img.height, 0,
      gl.RGBA, gl.UNSIGNED_BYTE, img);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    this.bytes += img.width * img.height * 4;
    img.close();
    return tex;
  }

  load(k, layer) {
    const key = `${k}/${layer}`;
    if (this.gpu.has(key)) return Promise.resolve(this.gpu.get(key));
    if (!this.loading.has(key)) {
      const spec = this.layerSpec(k, layer);
      const job = (async () => {
        const [pos, idx, rgb, aux] = await Promise.all([
          this._fetch(spec.pos).then((r) => r.arrayBuffer()),
          this._fetch(spec.idx).then((r) => r.arrayBuffer()),
          this._texture(spec.rgb, this.m.encoding === "srgb" && this.m.settings.blend_space === "linear"),
          this._texture(spec.aux, false)]);
        const gl = this.gl;
        const vao = gl.createVertexArray();
        gl.bindVertexArray(vao);
        const vbo = gl.createBuffer();
        gl.bindBuffer(gl.ARRAY_BUFFER, vbo);
        gl.bufferData(gl.ARRAY_BUFFER, pos, gl.STATIC_DRAW);
        gl.enableVertexAttribArray(0);
        gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 12, 0);
        const ibo = gl.createBuffer();
        gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ibo);
        gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, idx, gl.STATIC_DRAW);
        gl.bindVertexArray(null);
        this.bytes += pos.byteLength + idx.byteLength;
        const g = { vao, count: idx.byteLength / 4, rgb, aux, hasBeta: spec.has_beta };
        this.gpu.set(key, g);
        this.loading.delete(key);
        return g;
      })();
      this.loading.set(key, job);
    }
    return this.loading.get(key);
  }

  // the layers a frame in `mode` draws for view k
  layersFor(k, mode) {
    if (mode === "single") return ["single"];
    const L = this.views[k].layers;
    return L.reflection ? ["surface", "reflection"] : ["surface"];
  }

  isLoaded(k, mode) { return this.layersFor(k, mode).every((l) => this.gpu.has(`${k}/${l}`)); }

  async ensure(indices, mode) {
    await Promise.all(indices.flatMap((k) => this.layersFor(k, mode).map((l) => this.load(k, l))));
  }

  // --- render targets ----------------------------------------------------------------------------
  _tex(w, h, fmt) {
    const gl = this.gl;
    const t = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, t);
    gl.texStorage2D(gl.TEXTURE_2D, 1, fmt, w, h);
    for (const [p, v] of [[gl.TEXTURE_MIN_FILTER, gl.NEAREST], [gl.TEXTURE_MAG_FILTER, gl.NEAREST],
      [gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE], [gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE]]) {
      gl.texParameteri(gl.TEXTURE_2D, p, v);
    }
    return t;
  }

  _fbo(textures, depth = null) {
    const gl = this.gl;
    const f = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, f);
    textures.forEach((t, i) => gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0 + i,
      gl.TEXTURE_2D, t, 0));
    if (depth) gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, depth);
    gl.drawBuffers(textures.map((_, i) => gl.COLOR_ATTACHMENT0 + i));
    const st = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
    if (st !== gl.FRAMEBUFFER_COMPLETE) throw new Error(`framebuffer incomplete (0x${st.toString(16)})`);
    return { f, textures, n: textures.length };
  }

  _targets(w, h) {
    if (this.targets && this.targets.w === w && this.targets.h === h) return this.targets;
    const gl = this.gl;
    const F = gl.RGBA32F, R = gl.R32F;
    const t = { w, h };
    t.cost = this._fbo([this._tex(w, h, R)]);
    t.front = this._fbo([this._tex(w, h, R)]);
    t.blend = this._fbo([this._tex(w, h, F), this._tex(w, h, R)]);
    const depth = gl.createRenderbuffer();
    gl.bindRenderbuffer(gl.RENDERBUFFER, depth);
    gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, w, h);
    t.single = this._fbo([this._tex(w, h, F), this._tex(w, h, F)], depth);
    // push-pull pyramid: level 0 at full size, then ceil halves while both sides are >= 2
    t.levels = [];
    let lw = w, lh = h;
    for (let l = 0; l <= 12; l++) {
      t.levels.push({ w: lw, h: lh, push: this._fbo([this._tex(lw, lh, F), this._tex(lw, lh, R)]),
        pull: this._fbo([this._tex(lw, lh, F)]) });
      if (l === 12 || Math.min(lw, lh) < 2) break;
      lw = Math.ceil(lw / 2); lh = Math.ceil(lh / 2);
    }
    t.filled = [this._fbo([this._tex(w, h, F)]), this._fbo([this._tex(w, h, F)])];
    this.targets = t;
    return t;
  }

  _clear(fbo, value) {  // the whole target, also while a pass is scissored
    const gl = this.gl;
    const sc = gl.isEnabled(gl.SCISSOR_TEST);
    gl.disable(gl.SCISSOR_TEST);
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo.f);
    for (let i = 0; i < fbo.n; i++) gl.clearBufferfv(gl.COLOR, i, [value, value, value, value]);
    if (sc) gl.enable(gl.SCISSOR_TEST);
  }

  // (x, y, w, h) around the pixels whose blended beta is > 0, or null: IBRModel.render draws the
  // reflection layer only in the box of beta > 1e-4. Read from pyramid level <= 3 (1/8 size, a
  // conservative box a few pixels larger) to keep the read-back small.
  _betaBox(t) {
    const gl = this.gl;
    const l = Math.min(3, t.levels.length - 1), L = t.levels[l];
    gl.bindFramebuffer(gl.FRAMEBUFFER, L.push.f);
    gl.readBuffer(gl.COLOR_ATTACHMENT0);
    const px = new Float32Array(L.w * L.h * 4);
    gl.readPixels(0, 0, L.w, L.h, gl.RGBA, gl.FLOAT, px);
    let x0 = Infinity, y0 = Infinity, x1 = -1, y1 = -1;
    for (let y = 0; y < L.h; y++) {
      for (let x = 0; x < L.w; x++) {
        if (px[(y * L.w + x) * 4 + 3] > 1e-7) {
          if (x < x0) x0 = x; if (x > x1) x1 = x; if (y < y0) y0 = y; if (y > y1) y1 = y;
        }
      }
    }
    if (x1 < 0) return null;
    const sx = t.w / L.w, sy = t.h / L.h;
    const X0 = Math.max(0, Math.floor(x0 * sx) - 1), Y0 = Math.max(0, Math.floor(y0 * sy) - 1);
    const X1 = Math.min(t.w, Math.ceil((x1 + 1) * sx) + 1), Y1 = Math.min(t.h, Math.ceil((y1 + 1) * sy) + 1);
    return [X0, Y0, X1 - X0, Y1 - Y0];
  }

  _bindTex(unit, tex) {
    const gl = this.gl;
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(gl.TEXTURE_2D, tex);
  }

  _fullscreen(prog, fbo, w, h, uniforms) {
    const gl = this.gl;
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo ? fbo.f : null);
    gl.viewport(0, 0, w, h);
    gl.useProgram(prog.prog);
    setUniforms(gl, prog, uniforms);
    gl.bindVertexArray(this.emptyVao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }

  // --- one layer: the three passes (fuzzy) or per-view z-buffering ------------------------------
  _viewUniforms(k) {
    const v = this.views[k];
    return { S_k: glMat(sourceMatrix(v.cam)), t_k: v.cam.center, src_size: [v.cam.width, v.cam.height] };
  }

  _draw(prog, g, uniforms) {
    const gl = this.gl;
    gl.useProgram(prog.prog);
    setUniforms(gl, prog, uniforms);
    gl.bindVertexArray(g.vao);
    gl.drawElements(gl.TRIANGLES, g.count, gl.UNSIGNED_INT, 0);
  }

  _layerFuzzy(t, common, layer, items) {
    const gl = this.gl, s = this.s;
    gl.viewport(0, 0, t.w, t.h);
    gl.disable(gl.DEPTH_TEST); gl.disable(gl.CULL_FACE);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE);
    gl.blendEquation(gl.MIN);                       // pass 1: smallest IBR cost
    this._clear(t.cost, 1e30);
    for (const [k] of items) this._draw(this.p.cost, this.gpu.get(`${k}/${layer}`), { ...common, ...this._viewUniforms(k) });
    this._clear(t.front, 1e30);                     // pass 2: front-most depth within the margin
    this._bindTex(0, t.cost.textures[0]);
    for (const [k] of items) {
      this._draw(this.p.front, this.gpu.get(`${k}/${layer}`), { ...common, ...this._viewUniforms(k),
        cost_min: { int: 0 }, cost_margin: s.cost_margin });
    }
    gl.blendEquation(gl.FUNC_ADD);                  // pass 3: fuzzy depth test + Eq. 15 blend
    this._clear(t.blend, 0);
    this._bindTex(0, t.front.textures[0]);
    for (const [k, w] of items) {
      const g = this.gpu.get(`${k}/${layer}`);
      this._bindTex(1, g.rgb); this._bindTex(2, g.aux);
      this._draw(this.p.blend, g, { ...common, ...this._viewUniforms(k), front: { int: 0 },
        tex_rgba: { int: 1 }, tex_aux: { int: 2 }, depth_tol: s.depth_tol, w_k: w,
        has_beta: layer !== "reflection" && g.hasBeta });
    }
    gl.disable(gl.BLEND);
  }

  _layerPerView(t, common, layer, items) {
    const gl = this.gl;
    this._clear(t.blend, 0);
    for (const [k, w] of items) {
      const g = this.gpu.get(`${k}/${layer}`);
      gl.bindFramebuffer(gl.FRAMEBUFFER, t.single.f);
      gl.viewport(0, 0, t.w, t.h);
      gl.disable(gl.BLEND);
      gl.enable(gl.DEPTH_TEST);
      gl.depthFunc(gl.LESS);
      for (let i = 0; i < 2; i++) gl.clearBufferfv(gl.COLOR, i, [0, 0, 0, 0]);
      gl.clearBufferfv(gl.DEPTH, 0, [1.0]);
      this._bindTex(1, g.rgb); this._bindTex(2, g.aux);
      this._draw(this.p.single, g, { ...common, ...this._viewUniforms(k), tex_rgba: { int: 1 },
        tex_aux: { int: 2 } });
      gl.disable(gl.DEPTH_TEST);
      gl.enable(gl.BLEND);
      gl.blendFunc(gl.ONE, gl.ONE);
      gl.blendEquation(gl.FUNC_ADD);
      this._bindTex(0, t.single.textures[0]); this._bindTex(1, t.single.textures[1]);
      this._fullscreen(this.p.accum, t.blend, t.w, t.h, { rgba: { int: 0 }, geo: { int: 1 }, w_k: w });
      gl.disable(gl.BLEND);
    }
  }

  // normalise + push-pull hole filling (blend.fill_holes) of the blended layer into t.filled[slot]
  _fill(t, slot) {
    const s = this.s, L = t.levels;
    this._bindTex(0, t.blend.textures[0]); this._bindTex(1, t.blend.textures[1]);
    this._fullscreen(this.p.normalize, L[0].push, t.w, t.h, { acc: { int: 0 }, bacc: { int: 1 } });
    for (let l = 1; l < L.length; l++) {
      this._bindTex(0, L[l - 1].push.textures[0]); this._bindTex(1, L[l - 1].push.textures[1]);
      this._fullscreen(this.p.down, L[l].push, L[l].w, L[l].h, { src_cw: { int: 0 }, src_w: { int: 1 },
        ratio: [L[l - 1].w / L[l].w, L[l - 1].h / L[l].h] });
    }
    for (let l = L.length - 1; l >= 1; l--) {
      const top = l === L.length - 1;
      this._bindTex(0, L[l].push.textures[0]); this._bindTex(1, L[l].push.textures[1]);
      this._bindTex(2, top ? L[l].push.textures[0] : L[l + 1].pull.textures[0]);
      this._fullscreen(this.p.up, L[l].pull, L[l].w, L[l].h, { cw: { int: 0 }, w: { int: 1 },
        coarse: { int: 2 }, has_coarse: !top,
        ratio: top ? [1, 1] : [L[l + 1].w / L[l].w, L[l + 1].h / L[l].h] });
    }
    const one = L.length > 1 ? L[1] : L[0];
    this._bindTex(0, L[0].push.textures[0]); this._bindTex(1, L[0].push.textures[1]);
    this._bindTex(2, one.pull.textures[0]);
    const decay = s.hole_decay_px;  // a hole farther than decay_px (>= decay / 0.955 steps) leaves a = 1
    this._fullscreen(this.p.fill, t.filled[slot], t.w, t.h, { color: { int: 0 }, covered: { int: 1 },
      fill: { int: 2 }, ratio: [one.w / t.w, one.h / t.h], decay_px: decay,
      radius: { int: Math.min(8, Math.floor(decay / 0.955)) }, enabled: s.fill_holes && L.length > 1 });
  }

  // the views a frame of `cam` blends (IBRModel.select + the per_view cut), in blend order
  renderSelection(cam, mode = "composite", previous = null) {
    return chooseViews(cam, this.views.map((v) => v.cam), this.s, this.m.selection, previous).indices;
  }

  // --- a frame ------------------------------------------------------------------------------------
  // cam: {K, R, t, center, axis, width, height}; draws into the canvas (default framebuffer) at
  // the camera's size. Returns {ms, selected (indices), weights, timings}. Views must be loaded
  // (`ensure`); ones that are not yet are left out of this frame (`missing` counts them).
  render(cam, mode = "composite", previous = null) {
    const gl = this.gl;
    const t0 = performance.now();
    const sel = chooseViews(cam, this.views.map((v) => v.cam), this.s, this.m.selection, previous);
    const items = [];
    let missing = 0;
    sel.indices.forEach((k, i) => {
      if (this.isLoaded(k, mode)) items.push([k, sel.weights[i]]); else missing++;
    });
    const t = this._targets(cam.width, cam.height);
    const common = { P_n: glMat(projection(cam, this.m.near, this.m.far)),
      V_n: glMat(camFromWorld4(cam)), t_n: cam.center };
    const layerFn = this.s.visibility === "per_view" ? "_layerPerView" : "_layerFuzzy";
    const t1 = performance.now();
    const phases = {};  // with this.profile: GPU-synchronised time of each phase
    let tp = t1;
    const mark = (name) => {
      if (!this.profile) return;
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.FLOAT, new Float32Array(4));  // waits (float targets)
      const now = performance.now();
      phases[name] = (phases[name] || 0) + now - tp;
      tp = now;
    };
    this[layerFn](t, common, mode === "single" ? "single" : "surface", items);
    mark("layer0");
    this._fill(t, 0);
    mark("fill0");
    let items1 = mode === "single" ? [] : items.filter(([k]) => this.views[k].layers.reflection);
    const box = items1.length ? this._betaBox(t) : null;
    if (!box) items1 = [];
    if (items1.length) {
      gl.enable(gl.SCISSOR_TEST);
      gl.scissor(...box);
      this[layerFn](t, common, "reflection", items1);
      gl.disable(gl.SCISSOR_TEST);
      mark("layer1");
      this._fill(t, 1);
      mark("fill1");
    }
    this._bindTex(0, t.filled[0].textures[0]); this._bindTex(1, t.filled[1].textures[0]);
    this._fullscreen(this.p.compose, null, cam.width, cam.height, { layer0: { int: 0 },
      layer1: { int: 1 }, mode: { int: MODES[mode] ?? 0 }, has_layer1: items1.length > 0,
      decode_srgb: this.m.encoding === "srgb" && this.m.settings.blend_space !== "linear" });
    const px = new Uint8Array(4);
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);  // wait for the GPU: honest frame time
    const t2 = performance.now();
    return { ms: t2 - t0, select_ms: t1 - t0, gl_ms: t2 - t1, phases, selected: sel.indices,
      weights: sel.weights, drawn: items.map(([k]) => k), missing, box };
  }
}

export { LAYERS };
