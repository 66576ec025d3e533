// vcedit's before/after viewer for 3D Gaussian splatting scenes: WebGL2, no libraries, no network.
//
// Data. Every element with `data-vcedit-viewer` holds a JSON config (`script.vcv-config`) and one or two
// scenes (`script.vcv-scene`, base64). A scene is a list of 32-byte records, the `.splat` layout:
//   position f32×3 | scale f32×3 (standard deviations, linear) | colour RGBA u8×4 | rotation u8×4
// little-endian; colour is the SH degree-0 (DC) colour; A is the opacity; the rotation is the quaternion
// (w, x, y, z), each component mapped [-1, 1] → [0, 255]. With `data-sh1` the records are followed by 9
// bytes per Gaussian, its degree-1 SH coefficients (3 coefficients × RGB, each v mapped to 128 v + 128),
// which the vertex shader evaluates for the direction from the eye as the renderer does.
//
// Cameras are OpenCV pinhole cameras, as everywhere in vcedit: x right, y down, z forward; a world point p
// is at R p + t in the camera; fx, fy, cx, cy in pixels.
//
// Rendering follows vcedit's CPU renderer (crates/splat/src/render/project.rs). One instanced quad per
// Gaussian: the vertex shader projects the 3D covariance Σ to the screen (EWA: J R Σ Rᵀ Jᵀ plus a 0.3 px²
// low-pass) and spans the quad over ±3 standard deviations along the eigenvectors of that 2D covariance;
// the fragment shader evaluates the Gaussian, alpha = min(0.99, opacity · exp(-½ d²)), and blends it
// "over" what is already drawn (premultiplied alpha), farthest first. That order comes from a counting sort
// on 16-bit depth keys, redone on the CPU whenever the view changes.
//
// Before/after: the canvas shows the first scene left of a divider and the second right of it; the buttons
// put the divider at either edge (one scene) or in the middle, the slider anywhere. `#before`, `#after` or
// `#split` in the page's URL choose the starting mode.
(function () {
  'use strict';

  const RECORD_BYTES = 32;
  const SH1_BYTES = 9;
  const TEXELS_PER_GAUSSIAN = 6;
  const GAUSSIANS_PER_ROW = 512;  // 3072 texels wide: within every WebGL2 device's texture size
  const NEAR_PLANE = 0.01;
  const DEPTH_BUCKETS = 65536;
  const CULLED = 0xffffffff;

  const VERTEX_SHADER = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;

// Per Gaussian 6 RGBA32F texels: (x, y, z, opacity), (Σxx, Σxy, Σxz, Σyy), (Σyz, Σzz, -, -), (r, g, b, c3b),
// (c1r, c1g, c1b, c2r), (c2g, c2b, c3r, c3g): the DC colour and the degree-1 SH coefficients c1..c3.
uniform sampler2D u_gaussians;
uniform vec3 u_eye;          // the camera centre in the world
uniform mat3 u_rotation;     // world to camera
uniform vec3 u_translation;
uniform vec4 u_intrinsics;   // fx, fy, cx, cy in canvas pixels
uniform vec4 u_limits;       // x/z and y/z clamp for the Jacobian: (-x, +x, -y, +y) limits
uniform vec2 u_viewport;     // canvas size in pixels

in vec2 a_corner;            // quad corner in {-1, 1}²
in uint a_index;             // the Gaussian this instance draws

out vec4 v_color;            // rgb, opacity
out vec2 v_sigmas;           // position in the splat, in standard deviations along its axes

const float LOW_PASS = 0.3;
const float EXTENT = 3.0;

void main() {
  ivec2 texel = ivec2(int(a_index % ${GAUSSIANS_PER_ROW}u) * ${TEXELS_PER_GAUSSIAN}, int(a_index / ${GAUSSIANS_PER_ROW}u));
  vec4 t0 = texelFetch(u_gaussians, texel, 0);
  vec4 t1 = texelFetch(u_gaussians, texel + ivec2(1, 0), 0);
  vec4 t2 = texelFetch(u_gaussians, texel + ivec2(2, 0), 0);
  vec4 t3 = texelFetch(u_gaussians, texel + ivec2(3, 0), 0);
  vec4 t4 = texelFetch(u_gaussians, texel + ivec2(4, 0), 0);
  vec4 t5 = texelFetch(u_gaussians, texel + ivec2(5, 0), 0);

  vec3 p = u_rotation * t0.xyz + u_translation;
  if (p.z <= ${NEAR_PLANE}) {
    gl_Position = vec4(0.0, 0.0, 2.0, 1.0);  // outside the clip volume: nothing drawn
    return;
  }
  // EWA: the Jacobian of the perspective projection at the mean, with x/z and y/z clamped to 1.3 times
  // the half field of view as the CPU renderer does, so far off-screen Gaussians keep sane footprints.
  float fx = u_intrinsics.x, fy = u_intrinsics.y;
  vec2 tangent = clamp(p.xy / p.z, -u_limits.xz, u_limits.yw) * p.z;
  float z2 = p.z * p.z;
  mat3 jacobian = mat3(fx / p.z, 0.0, 0.0,
                       0.0, fy / p.z, 0.0,
                       -fx * tangent.x / z2, -fy * tangent.y / z2, 0.0);  // columns; third row zero
  mat3 sigma = mat3(t1.x, t1.y, t1.z,
                    t1.y, t1.w, t2.x,
                    t1.z, t2.x, t2.y);
  mat3 to_screen = jacobian * u_rotation;
  mat3 cov = to_screen * sigma * transpose(to_screen);
  float a = cov[0][0] + LOW_PASS, b = cov[0][1], c = cov[1][1] + LOW_PASS;

  // Eigen-decomposition of the 2D covariance: the quad's axes and half-lengths.
  float mid = 0.5 * (a + c);
  float radius = length(vec2(0.5 * (a - c), b));
  float major = mid + radius, minor = max(mid - radius, 0.1);
  vec2 axis = abs(b) > 1e-9 ? normalize(vec2(b, major - a)) : (a >= c ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
  vec2 center = vec2(fx * p.x / p.z + u_intrinsics.z, fy * p.y / p.z + u_intrinsics.w);
  vec2 pixel = center + EXTENT * (a_corner.x * sqrt(major) * axis + a_corner.y * sqrt(minor) * vec2(-axis.y, axis.x));

  // Pixels (y down) to clip space (y up).
  gl_Position = vec4(2.0 * pixel.x / u_viewport.x - 1.0, 1.0 - 2.0 * pixel.y / u_viewport.y, 0.0, 1.0);
  // SH degree 1 along the direction from the eye (the renderer's basis: -C1 y, C1 z, -C1 x), added to
  // the DC colour and clamped at 0 as the renderer clamps.
  vec3 d = normalize(t0.xyz - u_eye);
  vec3 sh1 = 0.48860251 * (-d.y * t4.xyz + d.z * vec3(t4.w, t5.xy) - d.x * vec3(t5.zw, t3.w));
  v_color = vec4(max(t3.rgb + sh1, 0.0), t0.w);
  v_sigmas = EXTENT * a_corner;
}`;

  const FRAGMENT_SHADER = `#version 300 es
precision highp float;

in vec4 v_color;
in vec2 v_sigmas;
out vec4 frag_color;

void main() {
  float power = 0.5 * dot(v_sigmas, v_sigmas);
  if (power > 4.5) discard;  // beyond 3 standard deviations
  float alpha = min(0.99, v_color.a * exp(-power));
  if (alpha < 1.0 / 255.0) discard;
  frag_color = vec4(v_color.rgb * alpha, alpha);
}`;

  // ---- vectors (arrays of 3 numbers) ----
  const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const normalize = (a) => scale(a, 1 / (Math.hypot(a[0], a[1], a[2]) || 1));

  // Rotates v by `angle` radians about the unit vector `axis` (Rodrigues).
  function rotate(v, axis, angle) {
    const c = Math.cos(angle), s = Math.sin(angle);
    return add(add(scale(v, c), scale(cross(axis, v), s)), scale(axis, dot(axis, v) * (1 - c)));
  }

  // ---- scene data ----

  // Decodes a base64 scene into the GPU layout (see the vertex shader) plus the positions for sorting.
  function decodeScene(base64, hasSh1) {
    const binary = atob(base64.trim());
    const bytes = new Uint8Array(binary.length);
    for (let i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
    const data = new DataView(bytes.buffer);
    const count = Math.floor(bytes.length / (RECORD_BYTES + (hasSh1 ? SH1_BYTES : 0)));
    const sh = (i, k) => hasSh1 ? (bytes[count * RECORD_BYTES + SH1_BYTES * i + k] - 128) / 128 : 0;
    const rows = Math.max(1, Math.ceil(count / GAUSSIANS_PER_ROW));
    const texels = new Float32Array(rows * GAUSSIANS_PER_ROW * TEXELS_PER_GAUSSIAN * 4);
    const positions = new Float32Array(3 * count);
    for (let i = 0; i < count; i++) {
      const o = i * RECORD_BYTES;
      const f = (k) => data.getFloat32(o + 4 * k, true);
      const [x, y, z, sx, sy, sz] = [f(0), f(1), f(2), f(3), f(4), f(5)];
      let [qw, qx, qy, qz] = [28, 29, 30, 31].map((k) => (bytes[o + k] - 128) / 128);
      const qn = Math.hypot(qw, qx, qy, qz) || 1;
      [qw, qx, qy, qz] = [qw / qn, qx / qn, qy / qn, qz / qn];
      // M = rot(q) diag(s), Σ = M Mᵀ.
      const m = [
        [(1 - 2 * (qy * qy + qz * qz)) * sx, 2 * (qx * qy - qw * qz) * sy, 2 * (qx * qz + qw * qy) * sz],
        [2 * (qx * qy + qw * qz) * sx, (1 - 2 * (qx * qx + qz * qz)) * sy, 2 * (qy * qz - qw * qx) * sz],
        [2 * (qx * qz - qw * qy) * sx, 2 * (qy * qz + qw * qx) * sy, (1 - 2 * (qx * qx + qy * qy)) * sz],
      ];
      const cov = (r, c) => dot(m[r], m[c]);
      texels.set([
        x, y, z, bytes[o + 27] / 255,
        cov(0, 0), cov(0, 1), cov(0, 2), cov(1, 1),
        cov(1, 2), cov(2, 2), 0, 0,
        bytes[o + 24] / 255, bytes[o + 25] / 255, bytes[o + 26] / 255, sh(i, 8),
        sh(i, 0), sh(i, 1), sh(i, 2), sh(i, 3),
        sh(i, 4), sh(i, 5), sh(i, 6), sh(i, 7),
      ], 4 * TEXELS_PER_GAUSSIAN * i);
      positions.set([x, y, z], 3 * i);
    }
    return { count, rows, texels, positions };
  }

  // Writes into `order` the Gaussians in front of the camera, farthest first, and returns how many: a
  // counting sort on 16-bit keys of the camera depth (one pass to count, one to place).
  function sortBackToFront(scene, rotation, translation, scratch) {
    const { positions, count } = scene;
    const [r0, r1, r2] = rotation[2];
    const t = translation[2];
    const { depths, keys, counts } = scratch;
    let near = Infinity, far = -Infinity;
    for (let i = 0; i < count; i++) {
      const z = r0 * positions[3 * i] + r1 * positions[3 * i + 1] + r2 * positions[3 * i + 2] + t;
      depths[i] = z;
      if (z > NEAR_PLANE) {
        near = Math.min(near, z);
        far = Math.max(far, z);
      }
    }
    counts.fill(0);
    const step = (DEPTH_BUCKETS - 1) / Math.max(far - near, 1e-9);
    let visible = 0;
    for (let i = 0; i < count; i++) {
      if (depths[i] > NEAR_PLANE) {
        const key = (DEPTH_BUCKETS - 1) - Math.floor((depths[i] - near) * step);  // far → small key
        keys[i] = key;
        counts[key]++;
        visible++;
      } else {
        keys[i] = CULLED;
      }
    }
    for (let k = 0, start = 0; k < DEPTH_BUCKETS; k++) {
      const n = counts[k];
      counts[k] = start;
      start += n;
    }
    for (let i = 0; i < count; i++) {
      if (keys[i] !== CULLED) scene.order[counts[keys[i]]++] = i;
    }
    return visible;
  }

  // ---- WebGL ----

  function compile(gl, type, source) {
    const shader = gl.createShader(type);
    gl.shaderSource(shader, source);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) {
      throw new Error('vcedit viewer: shader does not compile: ' + gl.getShaderInfoLog(shader));
    }
    return shader;
  }

  function linkProgram(gl) {
    const program = gl.createProgram();
    gl.attachShader(program, compile(gl, gl.VERTEX_SHADER, VERTEX_SHADER));
    gl.attachShader(program, compile(gl, gl.FRAGMENT_SHADER, FRAGMENT_SHADER));
    gl.bindAttribLocation(program, 0, 'a_corner');
    gl.bindAttribLocation(program, 1, 'a_index');
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS)) {
      throw new Error('vcedit viewer: shaders do not link: ' + gl.getProgramInfoLog(program));
    }
    return program;
  }

  // Uploads a decoded scene: its data texture, a buffer for the per-frame order, and the vertex array.
  function uploadScene(gl, scene, cornerBuffer) {
    scene.texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, scene.texture);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, GAUSSIANS_PER_ROW * TEXELS_PER_GAUSSIAN, scene.rows, 0,
      gl.RGBA, gl.FLOAT, scene.texels);
    scene.texels = null;  // on the GPU now
    scene.order = new Uint32Array(scene.count);
    scene.orderBuffer = gl.createBuffer();
    scene.vertexArray = gl.createVertexArray();
    gl.bindVertexArray(scene.vertexArray);
    gl.bindBuffer(gl.ARRAY_BUFFER, cornerBuffer);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
    gl.bindBuffer(gl.ARRAY_BUFFER, scene.orderBuffer);
    gl.bufferData(gl.ARRAY_BUFFER, scene.order, gl.DYNAMIC_DRAW);
    gl.enableVertexAttribArray(1);
    gl.vertexAttribIPointer(1, 1, gl.UNSIGNED_INT, 0, 0);
    gl.vertexAttribDivisor(1, 1);
    gl.bindVertexArray(null);
    scene.sortedFor = -1;  // the view version it was last sorted for
  }

  // ---- the viewer ----

  class Viewer {
    constructor(root) {
      this.root = root;
      this.config = JSON.parse(root.querySelector('script.vcv-config').textContent);
      this.canvas = root.querySelector('canvas');
      this.divider = root.querySelector('.vcv-divider');
      this.slider = root.querySelector('.vcv-split');
      const gl = this.canvas.getContext('webgl2', { alpha: false, antialias: false, preserveDrawingBuffer: true });
      if (!gl) {
        root.querySelector('.vcv-message').textContent = 'This browser has no WebGL2: the 3D view is not available.';
        console.error('vcedit viewer: WebGL2 is not available');
        return;
      }
      this.gl = gl;
      this.program = linkProgram(gl);
      this.uniforms = {};
      for (const name of ['u_gaussians', 'u_eye', 'u_rotation', 'u_translation', 'u_intrinsics', 'u_limits', 'u_viewport']) {
        this.uniforms[name] = gl.getUniformLocation(this.program, name);
      }
      const corners = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, corners);
      gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
      this.scenes = [...root.querySelectorAll('script.vcv-scene')].map((element) => {
        const scene = decodeScene(element.textContent, element.hasAttribute('data-sh1'));
        uploadScene(gl, scene, corners);
        return scene;
      });
      const most = Math.max(1, ...this.scenes.map((s) => s.count));
      this.scratch = { depths: new Float32Array(most), keys: new Uint32Array(most), counts: new Uint32Array(DEPTH_BUCKETS) };

      // The view: the camera's axes in world coordinates (the rows of R), its centre, and the pivot.
      const camera = this.config.camera;
      const rows = camera.rotation;
      this.home = {
        rows: rows.map((r) => r.slice()),
        center: scale([0, 1, 2].map((a) => dot([rows[0][a], rows[1][a], rows[2][a]], camera.translation)), -1),
        pivot: this.config.pivot.slice(),
      };
      this.up = normalize(this.config.up);
      this.homeDistance = Math.hypot(...sub(this.home.center, this.home.pivot)) || 1;
      this.resetView();
      this.split = 0.5;
      this.bindControls();
      const mode = { '#before': 'before', '#after': 'after', '#split': 'split' }[location.hash];
      this.show(mode || 'split');
    }

    resetView() {
      this.view = { rows: this.home.rows.map((r) => r.slice()), center: this.home.center.slice(), pivot: this.home.pivot.slice() };
      this.viewChanged();
    }

    viewChanged() {
      this.version = (this.version || 0) + 1;
      this.requestRender();
    }

    // Turns the camera about the pivot: horizontal drags about the world's up axis, vertical ones about
    // the camera's right axis (stopping short of the poles). Dragging right turns the scene right.
    orbit(dx, dy) {
      const v = this.view;
      const turn = (axis, angle) => {
        v.rows = v.rows.map((r) => rotate(r, axis, angle));
        v.center = add(v.pivot, rotate(sub(v.center, v.pivot), axis, angle));
      };
      turn(this.up, -0.008 * dx);
      const pitch = -0.008 * dy;
      if (Math.abs(dot(rotate(v.rows[2], v.rows[0], pitch), this.up)) < 0.98) turn(v.rows[0], pitch);
      this.viewChanged();
    }

    // Moves the camera towards (factor < 1) or away from the pivot.
    zoom(factor) {
      const v = this.view;
      const offset = sub(v.center, v.pivot);
      const distance = Math.hypot(...offset);
      const target = Math.min(Math.max(distance * factor, 1e-3 * this.homeDistance), 1e3 * this.homeDistance);
      v.center = add(v.pivot, scale(offset, target / (distance || 1)));
      this.viewChanged();
    }

    // Slides camera and pivot sideways so the scene follows the pointer.
    pan(dx, dy) {
      const v = this.view;
      const perPixel = Math.max(dot(sub(v.pivot, v.center), v.rows[2]), 1e-6) / this.intrinsics().fx;
      const shift = add(scale(v.rows[0], -dx * perPixel), scale(v.rows[1], -dy * perPixel));
      v.center = add(v.center, shift);
      v.pivot = add(v.pivot, shift);
      this.viewChanged();
    }

    // 'before' (first scene everywhere), 'after' (second scene), or 'split' (divider in the middle).
    show(mode) {
      this.setSplit({ before: 1, after: 0, split: 0.5 }[mode]);
    }

    setSplit(fraction) {
      this.split = this.scenes.length > 1 ? Math.min(Math.max(fraction, 0), 1) : 1;
      if (this.slider) this.slider.value = Math.round(100 * this.split);
      if (this.divider) this.divider.style.left = 100 * this.split + '%';
      this.root.dataset.mode = this.split === 1 ? 'before' : this.split === 0 ? 'after' : 'split';
      this.requestRender();
    }

    bindControls() {
      const canvas = this.canvas;
      let last = null;
      canvas.addEventListener('pointerdown', (e) => {
        last = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey };
        try { canvas.setPointerCapture(e.pointerId); } catch (_) { /* synthetic events have no pointer */ }
      });
      canvas.addEventListener('pointermove', (e) => {
        if (!last) return;
        const [dx, dy] = [e.clientX - last.x, e.clientY - last.y];
        last.x = e.clientX;
        last.y = e.clientY;
        const ratio = canvas.width / (canvas.clientWidth || canvas.width);
        if (last.pan) this.pan(dx * ratio, dy * ratio); else this.orbit(dx, dy);
      });
      const release = () => { last = null; };
      canvas.addEventListener('pointerup', release);
      canvas.addEventListener('pointercancel', release);
      canvas.addEventListener('contextmenu', (e) => e.preventDefault());
      canvas.addEventListener('wheel', (e) => {
        e.preventDefault();
        this.zoom(Math.exp(0.0015 * Math.max(-300, Math.min(300, e.deltaY))));
      }, { passive: false });
      canvas.addEventListener('dblclick', () => this.resetView());
      this.root.querySelectorAll('button[data-mode]').forEach((b) => b.addEventListener('click', () => this.show(b.dataset.mode)));
      this.root.querySelectorAll('button[data-action=reset]').forEach((b) => b.addEventListener('click', () => this.resetView()));
      if (this.slider) this.slider.addEventListener('input', () => this.setSplit(this.slider.value / 100));
      window.addEventListener('resize', () => this.requestRender());
    }

    // The reference camera's intrinsics scaled to the canvas.
    intrinsics() {
      const c = this.config.camera;
      const [sx, sy] = [this.canvas.width / c.width, this.canvas.height / c.height];
      return { fx: c.fx * sx, fy: c.fy * sy, cx: c.cx * sx, cy: c.cy * sy };
    }

    requestRender() {
      if (!this.gl || this.pending) return;
      this.pending = true;
      requestAnimationFrame(() => this.render());
    }

    // Draws now: the first scene left of the divider, the second right of it.
    render() {
      this.pending = false;
      const gl = this.gl, canvas = this.canvas;
      const ratio = window.devicePixelRatio || 1;
      const width = Math.max(1, Math.round(canvas.clientWidth * ratio));
      const height = Math.max(1, Math.round(canvas.clientHeight * ratio));
      if (canvas.width !== width || canvas.height !== height) [canvas.width, canvas.height] = [width, height];

      const bg = this.config.background;
      gl.viewport(0, 0, width, height);
      gl.disable(gl.SCISSOR_TEST);
      gl.clearColor(bg[0], bg[1], bg[2], 1);
      gl.clear(gl.COLOR_BUFFER_BIT);

      const v = this.view;
      const rotation = v.rows;
      const translation = scale([0, 1, 2].map((a) => dot(rotation[a], v.center)), -1);
      const k = this.intrinsics();
      const tanX = 0.5 * width / k.fx, tanY = 0.5 * height / k.fy;
      gl.useProgram(this.program);
      gl.uniformMatrix3fv(this.uniforms.u_rotation, false, [0, 1, 2].flatMap((c) => rotation.map((r) => r[c])));
      gl.uniform3fv(this.uniforms.u_translation, translation);
      gl.uniform3fv(this.uniforms.u_eye, v.center);
      gl.uniform4f(this.uniforms.u_intrinsics, k.fx, k.fy, k.cx, k.cy);
      gl.uniform4f(this.uniforms.u_limits, k.cx / k.fx + 0.3 * tanX, (width - k.cx) / k.fx + 0.3 * tanX,
        k.cy / k.fy + 0.3 * tanY, (height - k.cy) / k.fy + 0.3 * tanY);
      gl.uniform2f(this.uniforms.u_viewport, width, height);
      gl.uniform1i(this.uniforms.u_gaussians, 0);
      gl.activeTexture(gl.TEXTURE0);
      gl.enable(gl.BLEND);
      gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
      gl.enable(gl.SCISSOR_TEST);

      const divider = Math.round(this.split * width);
      const regions = [[0, divider], [divider, width]];
      this.scenes.forEach((scene, i) => {
        const [x0, x1] = regions[i];
        if (x1 <= x0 || scene.count === 0) return;
        if (scene.sortedFor !== this.version) {
          scene.visible = sortBackToFront(scene, rotation, translation, this.scratch);
          gl.bindBuffer(gl.ARRAY_BUFFER, scene.orderBuffer);
          gl.bufferSubData(gl.ARRAY_BUFFER, 0, scene.order, 0, scene.visible);
          scene.sortedFor = this.version;
        }
        gl.scissor(x0, 0, x1 - x0, height);
        gl.bindTexture(gl.TEXTURE_2D, scene.texture);
        gl.bindVertexArray(scene.vertexArray);
        gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, scene.visible);
      });
      gl.bindVertexArray(null);
    }
  }

  window.vceditViewers = window.vceditViewers || [];
  document.querySelectorAll('[data-vcedit-viewer]').forEach((root) => {
    if (root.vceditViewer) return;
    const viewer = new Viewer(root);
    root.vceditViewer = viewer;
    window.vceditViewers.push(viewer);
    if (viewer.gl) viewer.render();  // the first frame at once, so it is there when the page has loaded
  });
})();
