// vcedit's before/after viewer for 3D Gaussian splatting scenes: WebGL2, no libraries, no network.
//
// Data. Every element with `data-vcedit-viewer` holds a JSON config (`script.vcv-config`) and one or two
// scenes (`script.vcv-scene`, base64). A scene is a list of 32-byte records, the `.splat` layout:
//   position f32×3 | scale f32×3 (standard deviations, linear) | colour RGBA u8×4 | rotation u8×4
// little-endian; colour is the SH degree-0 (DC) colour; A is the opacity; the rotation is the quaternion
// (w, x, y, z), each component mapped [-1, 1] → [0, 255]. With `data-sh-degree="d"` (1 to 3) the records
// are followed by 3 · ((d + 1)² − 1) bytes per Gaussian, its SH coefficients above the DC term
// (coefficient-major, RGB inner, each v mapped to 128 v + 128), which the vertex shader evaluates for the
// direction from the eye with the basis of the renderer (crates/splat/src/render/sh.rs).
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
//
// Controls: the mouse orbits around a pivot, pans and zooms; with the canvas focused, keys fly the camera
// as SuperSplat's viewer does (W/S forward/back, A/D sideways, E/Q up/down along the world's up axis,
// Shift faster) and the arrow keys turn it in place, at speeds proportional to the distance from the first
// camera to the pivot, so small and large scenes feel alike. Frames are drawn only while a key is held or
// after something changed. The canvas takes the page's width (its height is capped by the window); the
// first camera is fitted into it without stretching, and "full screen" shows the viewer alone.
(function () {
  'use strict';

  const RECORD_BYTES = 32;
  const TEXELS_PER_GAUSSIAN = 4;
  const GAUSSIANS_PER_ROW = 512;  // 2048 texels wide: within every WebGL2 device's texture size (≥ 2048)
  // Fly controls: the view's share of the first camera's distance to the pivot covered per second, Shift's
  // factor, and the turning rate of the arrow keys.
  const FLY_SPEED = 0.5;
  const FLY_FAST = 4;
  const TURN_RADIANS_PER_SECOND = Math.PI / 3;
  const LONGEST_FLY_STEP_SECONDS = 0.1;  // a stalled frame must not jump the camera
  const FLY_KEYS = new Set(['KeyW', 'KeyS', 'KeyA', 'KeyD', 'KeyQ', 'KeyE', 'ArrowUp', 'ArrowDown', 'ArrowLeft', 'ArrowRight']);
  const NEAR_PLANE = 0.01;
  const DEPTH_BUCKETS = 65536;
  const CULLED = 0xffffffff;

  const VERTEX_SHADER = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;

// Per Gaussian 4 RGBA32F texels: (x, y, z, opacity), (Σxx, Σxy, Σxz, Σyy), (Σyz, Σzz, -, -), (r, g, b, -)
// with the DC colour; and u_sh_texels RGBA32UI texels in u_sh holding the SH bytes (little-endian words).
uniform sampler2D u_gaussians;
uniform highp usampler2D u_sh;
uniform int u_sh_degree;     // 0 to 3
uniform int u_sh_texels;     // per Gaussian in u_sh
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

// The view-dependent colour: the SH bands above DC at the unit direction d from the eye, with the basis
// constants and signs of the renderer's sh.rs (those of the 3DGS reference code).
vec3 sh_color(vec3 d) {
  if (u_sh_degree == 0) return vec3(0.0);
  ivec2 texel = ivec2(int(a_index % ${GAUSSIANS_PER_ROW}u) * u_sh_texels, int(a_index / ${GAUSSIANS_PER_ROW}u));
  uvec4 w0 = texelFetch(u_sh, texel, 0);
  uvec4 w1 = u_sh_texels > 1 ? texelFetch(u_sh, texel + ivec2(1, 0), 0) : uvec4(0u);
  uvec4 w2 = u_sh_texels > 2 ? texelFetch(u_sh, texel + ivec2(2, 0), 0) : uvec4(0u);
  uint words[12] = uint[12](w0.x, w0.y, w0.z, w0.w, w1.x, w1.y, w1.z, w1.w, w2.x, w2.y, w2.z, w2.w);
  float x = d.x, y = d.y, z = d.z, xx = x * x, yy = y * y, zz = z * z;
  float basis[15] = float[15](
    -0.48860251 * y, 0.48860251 * z, -0.48860251 * x,
    1.09254843 * x * y, -1.09254843 * y * z, 0.31539157 * (2.0 * zz - xx - yy), -1.09254843 * x * z,
    0.54627422 * (xx - yy),
    -0.59004359 * y * (3.0 * xx - yy), 2.89061144 * x * y * z, -0.45704580 * y * (4.0 * zz - xx - yy),
    0.37317633 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), -0.45704580 * x * (4.0 * zz - xx - yy),
    1.44530572 * z * (xx - yy), -0.59004359 * x * (xx - 3.0 * yy));
  int coefficients = (u_sh_degree + 1) * (u_sh_degree + 1) - 1;
  vec3 color = vec3(0.0);
  for (int j = 0; j < 15; j++) {
    if (j >= coefficients) break;
    vec3 c;
    for (int channel = 0; channel < 3; channel++) {
      int k = 3 * j + channel;  // the byte, 4 to a word
      uint byte = (words[k >> 2] >> (8u * uint(k & 3))) & 255u;
      c[channel] = (float(byte) - 128.0) / 128.0;
    }
    color += basis[j] * c;
  }
  return color;
}

void main() {
  ivec2 texel = ivec2(int(a_index % ${GAUSSIANS_PER_ROW}u) * ${TEXELS_PER_GAUSSIAN}, int(a_index / ${GAUSSIANS_PER_ROW}u));
  vec4 t0 = texelFetch(u_gaussians, texel, 0);
  vec4 t1 = texelFetch(u_gaussians, texel + ivec2(1, 0), 0);
  vec4 t2 = texelFetch(u_gaussians, texel + ivec2(2, 0), 0);
  vec4 t3 = texelFetch(u_gaussians, texel + ivec2(3, 0), 0);

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
  // The SH bands along the direction from the eye, added to the DC colour and clamped at 0 as the
  // renderer clamps.
  v_color = vec4(max(t3.rgb + sh_color(normalize(t0.xyz - u_eye)), 0.0), t0.w);
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

  // Bytes per Gaussian of the SH coefficients above DC up to `degree`.
  const shBytes = (degree) => 3 * ((degree + 1) * (degree + 1) - 1);

  // Decodes a base64 scene into the GPU layout (see the vertex shader) plus the positions for sorting.
  function decodeScene(base64, shDegree) {
    const binary = atob(base64.trim());
    const bytes = new Uint8Array(binary.length);
    for (let i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
    const data = new DataView(bytes.buffer);
    const perGaussianSh = shBytes(shDegree);
    const count = Math.floor(bytes.length / (RECORD_BYTES + perGaussianSh));
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
        bytes[o + 24] / 255, bytes[o + 25] / 255, bytes[o + 26] / 255, 0,
      ], 4 * TEXELS_PER_GAUSSIAN * i);
      positions.set([x, y, z], 3 * i);
    }
    // The SH bytes as they are, each Gaussian's padded to whole 16-byte texels; one empty texel when
    // there are none (the shader's sampler still needs a texture of its type).
    const shTexels = shDegree > 0 ? Math.ceil(perGaussianSh / 16) : 1;
    const shWidth = shDegree > 0 ? GAUSSIANS_PER_ROW * shTexels : 1;
    const shRows = shDegree > 0 ? rows : 1;
    const sh = new Uint8Array(shWidth * shRows * 16);
    const shStart = count * RECORD_BYTES;
    for (let i = 0; shDegree > 0 && i < count; i++) {
      sh.set(bytes.subarray(shStart + perGaussianSh * i, shStart + perGaussianSh * (i + 1)), 16 * shTexels * i);
    }
    return { count, rows, texels, positions, shDegree, shTexels, shWidth, shRows, sh: new Uint32Array(sh.buffer) };
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
    scene.shTexture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, scene.shTexture);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32UI, scene.shWidth, scene.shRows, 0, gl.RGBA_INTEGER, gl.UNSIGNED_INT, scene.sh);
    scene.texels = null;  // on the GPU now
    scene.sh = null;
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
      for (const name of ['u_gaussians', 'u_sh', 'u_sh_degree', 'u_sh_texels', 'u_eye', 'u_rotation', 'u_translation', 'u_intrinsics', 'u_limits', 'u_viewport']) {
        this.uniforms[name] = gl.getUniformLocation(this.program, name);
      }
      const corners = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, corners);
      gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
      this.scenes = [...root.querySelectorAll('script.vcv-scene')].map((element) => {
        const degree = Math.min(Math.max(parseInt(element.dataset.shDegree || '0', 10) || 0, 0), 3);
        const scene = decodeScene(element.textContent, degree);
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

    // Turns the camera where it stands: `yaw` radians to the right about the world's up axis (the horizon
    // stays level), `pitch` radians up about its right axis, stopping short of the poles. The pivot stays
    // straight ahead at the same distance, so orbiting afterwards turns around what is in view.
    turnInPlace(yaw, pitch) {
      const v = this.view;
      const reach = Math.hypot(...sub(v.pivot, v.center));
      v.rows = v.rows.map((r) => rotate(r, this.up, -yaw));
      if (pitch !== 0 && Math.abs(dot(rotate(v.rows[2], v.rows[0], pitch), this.up)) < 0.98) {
        v.rows = v.rows.map((r) => rotate(r, v.rows[0], pitch));
      }
      v.pivot = add(v.center, scale(v.rows[2], reach));
    }

    // One step of flying for `seconds` with the keys held now: W/S along the view, A/D along the camera's
    // right axis, E/Q along the world's up axis (camera and pivot together), arrows to turn.
    fly(seconds) {
      const held = (code) => (this.heldKeys.has(code) ? 1 : 0);
      const v = this.view;
      const move = add(add(
        scale(v.rows[2], held('KeyW') - held('KeyS')),
        scale(v.rows[0], held('KeyD') - held('KeyA'))),
        scale(this.up, held('KeyE') - held('KeyQ')));
      const length = Math.hypot(...move);
      if (length > 0) {
        const step = FLY_SPEED * this.homeDistance * seconds * (this.flyFast ? FLY_FAST : 1) / length;
        v.center = add(v.center, scale(move, step));
        v.pivot = add(v.pivot, scale(move, step));
      }
      const [yaw, pitch] = [held('ArrowRight') - held('ArrowLeft'), held('ArrowUp') - held('ArrowDown')];
      if (yaw !== 0 || pitch !== 0) {
        const turn = TURN_RADIANS_PER_SECOND * seconds;
        this.turnInPlace(turn * yaw, turn * pitch);
      }
      this.version = (this.version || 0) + 1;
    }

    // Flies one step per animation frame, by the time since the last one, while a key is held; the loop
    // ends with the last key released, so an idle viewer draws nothing.
    startFlying() {
      if (this.flying) return;
      this.flying = true;
      let last = performance.now();
      const frame = (now) => {
        if (this.heldKeys.size === 0) {
          this.flying = false;
          return;
        }
        const seconds = Math.min(Math.max(now - last, 0) / 1000, LONGEST_FLY_STEP_SECONDS);
        last = now;
        this.fly(seconds);
        this.render();
        requestAnimationFrame(frame);
      };
      requestAnimationFrame(frame);
    }

    isFullscreen() {
      return document.fullscreenElement === this.root;
    }

    toggleFullscreen() {
      if (this.isFullscreen()) {
        document.exitFullscreen();
        return;
      }
      // Keys fly the camera at once in full screen; a refusal (no user gesture, or a frame that may not
      // go full screen) leaves the page as it is, as the browser reports it.
      this.root.requestFullscreen().then(() => this.canvas.focus(), () => {});
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
      // The canvas follows the page's width and the full-screen switch without a window resize.
      if (window.ResizeObserver) new ResizeObserver(() => this.requestRender()).observe(canvas);

      // Keys act only while the canvas has the focus, so typing elsewhere on the page moves nothing; with
      // Ctrl, Alt or Meta they stay the browser's shortcuts.
      this.heldKeys = new Set();
      this.flyFast = false;
      canvas.addEventListener('keydown', (e) => {
        if (e.ctrlKey || e.altKey || e.metaKey) return;
        this.flyFast = e.shiftKey;
        if (!FLY_KEYS.has(e.code)) return;
        e.preventDefault();  // arrows would scroll the page
        this.heldKeys.add(e.code);
        this.startFlying();
      });
      canvas.addEventListener('keyup', (e) => {
        this.flyFast = e.shiftKey;
        this.heldKeys.delete(e.code);
      });
      // A key released while the focus was elsewhere sends its keyup there.
      canvas.addEventListener('blur', () => this.heldKeys.clear());

      const fullscreen = this.root.querySelector('button[data-action=fullscreen]');
      if (fullscreen && document.fullscreenEnabled && this.root.requestFullscreen) {
        fullscreen.hidden = false;
        fullscreen.addEventListener('click', () => this.toggleFullscreen());
        // Also when Escape (the browser's own way out) leaves full screen.
        document.addEventListener('fullscreenchange', () => {
          fullscreen.textContent = this.isFullscreen() ? 'exit full screen' : 'full screen';
          this.requestRender();
        });
      }
    }

    // The reference camera's intrinsics fitted into the canvas: scaled by one factor so its whole image
    // shows (the canvas's other axis sees more of the scene, nothing is stretched), centred.
    intrinsics() {
      const c = this.config.camera;
      const [width, height] = [this.canvas.width, this.canvas.height];
      const s = Math.min(width / c.width, height / c.height);
      return {
        fx: c.fx * s, fy: c.fy * s,
        cx: c.cx * s + 0.5 * (width - c.width * s), cy: c.cy * s + 0.5 * (height - c.height * s),
      };
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
      gl.uniform1i(this.uniforms.u_sh, 1);
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
        gl.uniform1i(this.uniforms.u_sh_degree, scene.shDegree);
        gl.uniform1i(this.uniforms.u_sh_texels, scene.shTexels);
        gl.activeTexture(gl.TEXTURE1);
        gl.bindTexture(gl.TEXTURE_2D, scene.shTexture);
        gl.activeTexture(gl.TEXTURE0);
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
