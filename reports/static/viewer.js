/* cobgs report: a WebGL2 Gaussian-splat viewer (written for this project; no library).

   What it draws is what cobgs.rasterize draws, up to the differences the report states:
   - each Gaussian's 3D covariance R S S^T R^T is projected in the vertex shader with the
     rasterizer's Jacobian (x/z, y/z clamped to the frustum widened by 0.3 of its half
     width), plus the 0.3 px^2 low-pass on the diagonal;
   - the quad is the square of half side ceil(3 sqrt(lambda_max)) around the projected
     mean (the rasterizer's radius); the fragment shader evaluates
     alpha = min(0.99, opacity exp(-d^T conic d / 2)) at the pixel centre and drops
     alpha < 1/255, as the rasterizer does;
   - colours are premultiplied and blended back to front (ONE, ONE_MINUS_SRC_ALPHA) over
     the scene's background; the order is an exact sort of the camera-space depth of the
     means (two 16-bit radix passes over the float bits), computed in a worker, off the
     main thread;
   - SH degree 0 only; the data are quantised (cobgs/render/splat_pack.py: 21 bytes a Gaussian).
   Everything works from file:// (the Gaussians come as base64 in script files). */
(function () {
  "use strict";

  var SPLATS = (window.COBGS_SPLATS = window.COBGS_SPLATS || {});
  var NEAR = 0.01, LOWPASS = 0.3, SLACK = 0.3, ROW = 1024;
  var MODES = ["object", "removed", "labels", "scene"];

  // -- data -------------------------------------------------------------------------------
  function loadScript(src) {
    return new Promise(function (resolve, reject) {
      var s = document.createElement("script");
      s.src = src;
      s.onload = function () { resolve(); };
      s.onerror = function () { reject(new Error("could not load " + src)); };
      document.head.appendChild(s);
    });
  }

  function bytesOf(b64) {
    var bin = atob(b64), out = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out;
  }

  // The inverse of cobgs.render.splat_pack.pack: float32 arrays of the decoded Gaussians, and the
  // 16 floats per Gaussian the shaders read (centre + opacity, covariance, label, colour).
  function decode(header, bytes) {
    var n = header.count, at = 0;
    if (bytes.length !== n * header.bytes_per_gaussian)
      throw new Error("splat data: expected " + n * header.bytes_per_gaussian + " bytes, got " + bytes.length);
    var buf = bytes.buffer, off = bytes.byteOffset;
    function view(Type, count, size) {
      var a;
      if ((off + at) % size === 0) a = new Type(buf, off + at, count);
      else a = new Type(bytes.slice(at, at + count * size).buffer);
      at += count * size;
      return a;
    }
    var pos = view(Uint16Array, 3 * n, 2), ls = view(Uint16Array, 3 * n, 2), rot = view(Int8Array, 4 * n, 1);
    var rgb = view(Uint8Array, 3 * n, 1), op = view(Uint8Array, n, 1), lab = view(Uint8Array, n, 1);
    var lo = header.lo, hi = header.hi, lsLo = header.ls_lo, lsHi = header.ls_hi, rgbHi = header.rgb_hi;
    var means = new Float32Array(3 * n), tex = new Float32Array(16 * n), labels = new Uint8Array(n);
    for (var i = 0; i < n; i++) {
      var x = lo[0] + (pos[3 * i] / 65535) * (hi[0] - lo[0]);
      var y = lo[1] + (pos[3 * i + 1] / 65535) * (hi[1] - lo[1]);
      var z = lo[2] + (pos[3 * i + 2] / 65535) * (hi[2] - lo[2]);
      means[3 * i] = x; means[3 * i + 1] = y; means[3 * i + 2] = z;
      var s0 = Math.exp(Math.fround(lsLo + (ls[3 * i] / 65535) * (lsHi - lsLo)));
      var s1 = Math.exp(Math.fround(lsLo + (ls[3 * i + 1] / 65535) * (lsHi - lsLo)));
      var s2 = Math.exp(Math.fround(lsLo + (ls[3 * i + 2] / 65535) * (lsHi - lsLo)));
      var qw = rot[4 * i] / 127, qx = rot[4 * i + 1] / 127, qy = rot[4 * i + 2] / 127, qz = rot[4 * i + 3] / 127;
      var qn = Math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz) || 1;
      qw /= qn; qx /= qn; qy /= qn; qz /= qn;
      // rotation matrix of (w, x, y, z), rows
      var r00 = 1 - 2 * (qy * qy + qz * qz), r01 = 2 * (qx * qy - qw * qz), r02 = 2 * (qx * qz + qw * qy);
      var r10 = 2 * (qx * qy + qw * qz), r11 = 1 - 2 * (qx * qx + qz * qz), r12 = 2 * (qy * qz - qw * qx);
      var r20 = 2 * (qx * qz - qw * qy), r21 = 2 * (qy * qz + qw * qx), r22 = 1 - 2 * (qx * qx + qy * qy);
      // M = R S; covariance = M M^T
      var m00 = r00 * s0, m01 = r01 * s1, m02 = r02 * s2;
      var m10 = r10 * s0, m11 = r11 * s1, m12 = r12 * s2;
      var m20 = r20 * s0, m21 = r21 * s1, m22 = r22 * s2;
      var t = 16 * i;
      tex[t] = x; tex[t + 1] = y; tex[t + 2] = z; tex[t + 3] = op[i] / 255;
      tex[t + 4] = m00 * m00 + m01 * m01 + m02 * m02;
      tex[t + 5] = m00 * m10 + m01 * m11 + m02 * m12;
      tex[t + 6] = m00 * m20 + m01 * m21 + m02 * m22;
      tex[t + 7] = m10 * m10 + m11 * m11 + m12 * m12;
      tex[t + 8] = m10 * m20 + m11 * m21 + m12 * m22;
      tex[t + 9] = m20 * m20 + m21 * m21 + m22 * m22;
      tex[t + 10] = lab[i];
      tex[t + 12] = (rgb[3 * i] / 255) * rgbHi;
      tex[t + 13] = (rgb[3 * i + 1] / 255) * rgbHi;
      tex[t + 14] = (rgb[3 * i + 2] / 255) * rgbHi;
      labels[i] = lab[i];
    }
    return { count: n, means: means, tex: tex, labels: labels };
  }

  // -- depth sort, off the main thread ----------------------------------------------------
  // Back-to-front order of the Gaussians in front of the near plane, by the camera-space
  // depth of their means: an exact sort (float bits of positive numbers sort as integers),
  // ties in reverse index order (front to back they would come in index order).
  function sorterBody() {
    var means = null, labels = null, n = 0;
    function sort(m) {
      var v = m.view, mode = m.mode, near = m.near;
      var keys = new Uint32Array(n), idx = new Uint32Array(n), f = new Float32Array(1), u = new Uint32Array(f.buffer);
      var k = 0;
      for (var i = 0; i < n; i++) {
        var l = labels[i];
        if ((mode === 0 && l !== 1) || (mode === 1 && l === 1)) continue;  // object alone / removed
        var z = v[8] * means[3 * i] + v[9] * means[3 * i + 1] + v[10] * means[3 * i + 2] + v[11];
        if (!(z > near)) continue;
        f[0] = z;
        keys[k] = u[0];
        idx[k] = i;
        k++;
      }
      var tmpK = new Uint32Array(k), tmpI = new Uint32Array(k), count = new Uint32Array(65536);
      // LSD radix: low 16 bits, then high 16 bits (each pass stable)
      for (var pass = 0; pass < 2; pass++) {
        var shift = pass * 16, srcK = pass ? tmpK : keys, srcI = pass ? tmpI : idx;
        var dstK = pass ? keys : tmpK, dstI = pass ? idx : tmpI;
        count.fill(0);
        for (i = 0; i < k; i++) count[(srcK[i] >>> shift) & 65535]++;
        var sum = 0;
        for (i = 0; i < 65536; i++) { var c = count[i]; count[i] = sum; sum += c; }
        for (i = 0; i < k; i++) {
          var d = count[(srcK[i] >>> shift) & 65535]++;
          dstK[d] = srcK[i];
          dstI[d] = srcI[i];
        }
      }
      var order = new Uint32Array(k);
      for (i = 0; i < k; i++) order[i] = idx[k - 1 - i];
      return order;
    }
    return {
      load: function (m) { means = m.means; labels = m.labels; n = labels.length; },
      sort: sort,
    };
  }

  function workerSource() {
    return "var S = (" + sorterBody.toString() + ")();\n" +
      "onmessage = function (e) { var m = e.data; if (m.means) { S.load(m); return; }\n" +
      "  var o = S.sort(m); postMessage({ token: m.token, order: o }, [o.buffer]); };\n";
  }

  // One sorter per model: a worker when the page may start one (blob URL), else the same
  // code on the main thread.
  function Sorter(model) {
    this.token = 0;
    this.pending = {};
    var self = this;
    try {
      var url = URL.createObjectURL(new Blob([workerSource()], { type: "text/javascript" }));
      this.worker = new Worker(url);
      URL.revokeObjectURL(url);
      this.worker.onmessage = function (e) {
        var p = self.pending[e.data.token];
        delete self.pending[e.data.token];
        if (p) p(e.data.order);
      };
      this.worker.postMessage({ means: model.means.slice(), labels: model.labels.slice() });
    } catch (err) {
      this.worker = null;
      this.local = sorterBody();
      this.local.load({ means: model.means, labels: model.labels });
    }
  }
  Sorter.prototype.sort = function (view, mode) {
    var msg = { view: view, mode: mode, near: NEAR, token: ++this.token };
    if (!this.worker) return Promise.resolve(this.local.sort(msg));
    var self = this;
    return new Promise(function (resolve) {
      self.pending[msg.token] = resolve;
      self.worker.postMessage(msg);
    });
  };
  Sorter.prototype.close = function () { if (this.worker) this.worker.terminate(); };

  // -- WebGL ------------------------------------------------------------------------------
  var VS = [
    "#version 300 es",
    "precision highp float; precision highp int; precision highp sampler2D;",
    "uniform sampler2D splats;",
    "uniform highp usampler2D order;",  // back-to-front Gaussian indices
    "uniform mat4 view;",
    "uniform vec4 intr;", // fx, fy, cx, cy
    "uniform vec4 lims;", // lim_xp, lim_xn, lim_yp, lim_yn
    "uniform vec2 size;",
    "uniform int mode;",
    "flat out vec4 vColor;",
    "flat out vec3 vConic;",
    "flat out vec2 vCenter;",
    "void main() {",
    // Six vertices (two triangles) per Gaussian, one non-instanced draw: SwiftShader runs
    // each instance of an instanced draw as a draw of its own (measured ~15 us each).
    "  int slot = gl_VertexID / 6, v = gl_VertexID - slot * 6;",
    "  vec2 corner = vec2((v == 1 || v == 4 || v == 5) ? 1.0 : -1.0, (v == 2 || v == 3 || v == 5) ? 1.0 : -1.0);",
    "  int i = int(texelFetch(order, ivec2(slot & " + (ROW - 1) + ", slot >> " + Math.log2(ROW) + "), 0).r);",
    "  ivec2 b = ivec2((i & " + (ROW - 1) + ") * 4, i >> " + Math.log2(ROW) + ");",
    "  vec4 t0 = texelFetch(splats, b, 0), t1 = texelFetch(splats, b + ivec2(1, 0), 0);",
    "  vec4 t2 = texelFetch(splats, b + ivec2(2, 0), 0), t3 = texelFetch(splats, b + ivec2(3, 0), 0);",
    "  vec4 pc = view * vec4(t0.xyz, 1.0);",
    "  gl_Position = vec4(0.0, 0.0, 2.0, 1.0);", // culled unless set below
    "  if (!(pc.z > " + NEAR + ")) return;",
    "  float z = pc.z, rx = pc.x / z, ry = pc.y / z;",
    "  float tx = z * clamp(rx, -lims.y, lims.x), ty = z * clamp(ry, -lims.w, lims.z);",
    "  mat3 J = mat3(intr.x / z, 0.0, 0.0, 0.0, intr.y / z, 0.0, -intr.x * tx / (z * z), -intr.y * ty / (z * z), 0.0);",
    "  mat3 S = mat3(t1.x, t1.y, t1.z, t1.y, t1.w, t2.x, t1.z, t2.x, t2.y);",
    "  mat3 T = J * mat3(view);",
    "  mat3 C = T * S * transpose(T);",
    "  float a = C[0][0] + " + LOWPASS.toFixed(1) + ", bb = C[0][1], c = C[1][1] + " + LOWPASS.toFixed(1) + ";",
    "  float det = a * c - bb * bb;",
    "  if (!(det > 0.0)) return;",
    "  float mid = 0.5 * (a + c);",
    "  float r = ceil(3.0 * sqrt(mid + sqrt(max(0.1, mid * mid - det))));",
    "  vec2 m = vec2(intr.x * rx + intr.z, intr.y * ry + intr.w);",
    "  if (m.x + r <= 0.0 || m.x - r >= size.x || m.y + r <= 0.0 || m.y - r >= size.y) return;",
    // The quad: the rectangle along the ellipse's axes that holds every pixel centre with
    // alpha >= 1/255 (q = d^T conic d <= 2 ln(255 opacity)). No 3-sigma cap: the
    // rasterizer draws those pixels too wherever the tiles of its 3-sigma square reach
    // (measured on the demo scene: a 3-sigma cap doubled the mean error, for 7% more fps).
    "  float q = 2.0 * log(255.0 * t0.w);",
    "  if (!(q > 0.0)) return;",
    "  float disc = sqrt(max(0.0, mid * mid - det));",
    "  float l1 = mid + disc, l2 = max(mid - disc, 0.0);",
    "  vec2 e1 = abs(bb) > 1e-12 ? normalize(vec2(bb, l1 - a)) : (a >= c ? vec2(1.0, 0.0) : vec2(0.0, 1.0));",
    "  vec2 e2 = vec2(-e1.y, e1.x);",
    "  vec2 ax1 = e1 * sqrt(l1 * q) * 1.001 + e1 * 0.01, ax2 = e2 * sqrt(l2 * q) * 1.001 + e2 * 0.01;",
    "  vec3 rgb = t3.rgb;",
    "  if (mode == 2) {",  // labels
    "    float luma = dot(rgb, vec3(0.299, 0.587, 0.114));",
    "    rgb = t2.z > 0.5 ? 0.35 * rgb + 0.65 * vec3(1.0, 0.55, 0.1) : 0.55 * luma * vec3(0.75, 0.85, 1.0);",
    "  }",
    "  vColor = vec4(rgb, t0.w);",
    "  vConic = vec3(c, -bb, a) / det;",
    "  vCenter = m;",
    "  vec2 p = m + corner.x * ax1 + corner.y * ax2;",
    "  gl_Position = vec4(2.0 * p.x / size.x - 1.0, 1.0 - 2.0 * p.y / size.y, 0.0, 1.0);",
    "}",
  ].join("\n");

  var FS = [
    "#version 300 es",
    "precision highp float;",
    "uniform vec2 size;",
    "flat in vec4 vColor;",
    "flat in vec3 vConic;",
    "flat in vec2 vCenter;",
    "out vec4 frag;",
    "void main() {",
    "  vec2 d = vec2(gl_FragCoord.x, size.y - gl_FragCoord.y) - vCenter;", // pixel centre - mean
    "  float power = -0.5 * (vConic.x * d.x * d.x + vConic.z * d.y * d.y) - vConic.y * d.x * d.y;",
    "  if (power > 0.0) discard;",
    "  float alpha = min(0.99, vColor.a * exp(power));",
    "  if (alpha < 1.0 / 255.0) discard;",
    "  frag = vec4(vColor.rgb * alpha, alpha);",
    "}",
  ].join("\n");

  // Copies the float accumulation target to the canvas (one full-screen triangle).
  var COPY_VS = "#version 300 es\nvoid main() { vec2 p = vec2(gl_VertexID == 1 ? 3.0 : -1.0, gl_VertexID == 2 ? 3.0 : -1.0);" +
    " gl_Position = vec4(p, 0.0, 1.0); }";
  var COPY_FS = "#version 300 es\nprecision highp float; uniform sampler2D acc; out vec4 frag;" +
    " void main() { frag = vec4(texelFetch(acc, ivec2(gl_FragCoord.xy), 0).rgb, 1.0); }";

  function program(gl, vs, fs) {
    var prog = gl.createProgram();
    gl.attachShader(prog, compile(gl, gl.VERTEX_SHADER, vs));
    gl.attachShader(prog, compile(gl, gl.FRAGMENT_SHADER, fs));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error("program: " + gl.getProgramInfoLog(prog));
    return prog;
  }

  function compile(gl, type, src) {
    var s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error("shader: " + gl.getShaderInfoLog(s));
    return s;
  }

  // One canvas: one WebGL2 context, the models shown in it (uploaded once each).
  function Canvas(canvas, background) {
    var gl = canvas.getContext("webgl2", { antialias: false, alpha: false, depth: false, premultipliedAlpha: true,
                                          preserveDrawingBuffer: true });
    if (!gl) throw new Error("WebGL2 is not available in this browser");
    this.gl = gl;
    this.canvas = canvas;
    this.background = background;
    var prog = program(gl, VS, FS);
    this.prog = prog;
    // Blending into a half-float target, then one copy to the 8-bit canvas: blending in the
    // canvas itself rounds every layer to 1/255 (measured on the demo scene: mean error
    // 0.76 levels against the rasterizer, 0.06 with the float target).
    this.floatTarget = !!gl.getExtension("EXT_color_buffer_float");
    if (this.floatTarget) {
      this.copyProg = program(gl, COPY_VS, COPY_FS);
      this.copyLoc = gl.getUniformLocation(this.copyProg, "acc");
      this.accTex = gl.createTexture();
      this.fbo = gl.createFramebuffer();
      this.accSize = [0, 0];
    }
    this.loc = {};
    var self = this;
    ["splats", "order", "view", "intr", "lims", "size", "mode"].forEach(function (u) { self.loc[u] = gl.getUniformLocation(prog, u); });
    this.vao = gl.createVertexArray();  // no attributes: the vertex shader reads textures
    this.order = gl.createTexture();
    this.orderRows = 0;
    this.textures = {};
    this.count = 0;
  }
  Canvas.prototype.upload = function (key, model) {
    if (this.textures[key]) return;
    var gl = this.gl, rows = Math.max(1, Math.ceil(model.count / ROW));
    var most = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    if (rows > most) throw new Error(model.count.toLocaleString() + " Gaussians need a " + (4 * ROW) + "x" + rows +
                                     " texture; this browser allows " + most + " rows (report with a smaller --viewer-mb)");
    var data = new Float32Array(ROW * 4 * rows * 4);
    data.set(model.tex);
    var tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, ROW * 4, rows, 0, gl.RGBA, gl.FLOAT, data);
    this.textures[key] = tex;
  };
  Canvas.prototype.setOrder = function (order) {
    var gl = this.gl, rows = Math.max(1, Math.ceil(order.length / ROW));
    var data = new Uint32Array(rows * ROW);
    data.set(order);
    gl.bindTexture(gl.TEXTURE_2D, this.order);
    if (rows !== this.orderRows) {
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.R32UI, ROW, rows, 0, gl.RED_INTEGER, gl.UNSIGNED_INT, data);
      this.orderRows = rows;
    } else {
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, ROW, rows, gl.RED_INTEGER, gl.UNSIGNED_INT, data);
    }
    this.count = order.length;
  };
  // cam: {w2c: 16 numbers row-major (OpenCV axes), K: [fx, fy, cx, cy]} at the canvas size
  Canvas.prototype.target = function (w, h) {
    var gl = this.gl;
    if (!this.floatTarget) return;
    if (this.accSize[0] !== w || this.accSize[1] !== h) {
      gl.bindTexture(gl.TEXTURE_2D, this.accTex);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA16F, w, h, 0, gl.RGBA, gl.HALF_FLOAT, null);
      gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo);
      gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, this.accTex, 0);
      if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) {
        this.floatTarget = false;  // not renderable here: blend in the canvas
        gl.bindFramebuffer(gl.FRAMEBUFFER, null);
        return;
      }
      this.accSize = [w, h];
    }
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo);
  };
  Canvas.prototype.draw = function (key, cam, mode) {
    var gl = this.gl, w = this.canvas.width, h = this.canvas.height, bg = this.background;
    this.target(w, h);
    gl.viewport(0, 0, w, h);
    gl.clearColor(bg[0], bg[1], bg[2], 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    if (this.textures[key] && this.count) this.splat(key, cam, mode, w, h);
    if (this.floatTarget) {
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.disable(gl.BLEND);
      gl.useProgram(this.copyProg);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, this.accTex);
      gl.uniform1i(this.copyLoc, 0);
      gl.bindVertexArray(this.vao);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
      gl.bindVertexArray(null);
    }
  };
  Canvas.prototype.splat = function (key, cam, mode, w, h) {
    var gl = this.gl;
    gl.useProgram(this.prog);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.textures[key]);
    gl.uniform1i(this.loc.splats, 0);
    gl.activeTexture(gl.TEXTURE1);
    gl.bindTexture(gl.TEXTURE_2D, this.order);
    gl.uniform1i(this.loc.order, 1);
    var v = cam.w2c;
    gl.uniformMatrix4fv(this.loc.view, false, [v[0], v[4], v[8], 0, v[1], v[5], v[9], 0, v[2], v[6], v[10], 0,
                                               v[3], v[7], v[11], 1]);
    var K = cam.K;
    gl.uniform4f(this.loc.intr, K[0], K[1], K[2], K[3]);
    gl.uniform4f(this.loc.lims, (w - K[2]) / K[0] + SLACK * 0.5 * w / K[0], K[2] / K[0] + SLACK * 0.5 * w / K[0],
                 (h - K[3]) / K[1] + SLACK * 0.5 * h / K[1], K[3] / K[1] + SLACK * 0.5 * h / K[1]);
    gl.uniform2f(this.loc.size, w, h);
    gl.uniform1i(this.loc.mode, MODES.indexOf(mode));
    gl.bindVertexArray(this.vao);
    gl.drawArrays(gl.TRIANGLES, 0, 6 * this.count);
    gl.bindVertexArray(null);
  };

  // -- camera maths (row-major 4x4 world-to-camera, OpenCV axes) -------------------------
  function invRigid(m) {
    // [R t; 0 1]^-1 = [R^T, -R^T t]
    return [m[0], m[4], m[8], -(m[0] * m[3] + m[4] * m[7] + m[8] * m[11]),
            m[1], m[5], m[9], -(m[1] * m[3] + m[5] * m[7] + m[9] * m[11]),
            m[2], m[6], m[10], -(m[2] * m[3] + m[6] * m[7] + m[10] * m[11]),
            0, 0, 0, 1];
  }
  function rotAxis(axis, angle) { // 3x3 row-major (Rodrigues)
    var x = axis[0], y = axis[1], z = axis[2], n = Math.hypot(x, y, z) || 1;
    x /= n; y /= n; z /= n;
    var c = Math.cos(angle), s = Math.sin(angle), t = 1 - c;
    return [t * x * x + c, t * x * y - s * z, t * x * z + s * y,
            t * x * y + s * z, t * y * y + c, t * y * z - s * x,
            t * x * z - s * y, t * y * z + s * x, t * z * z + c];
  }
  function mul3v(R, v) {
    return [R[0] * v[0] + R[1] * v[1] + R[2] * v[2], R[3] * v[0] + R[4] * v[1] + R[5] * v[2],
            R[6] * v[0] + R[7] * v[1] + R[8] * v[2]];
  }
  // camera-to-world as {R (columns = camera axes in world), c (centre)}
  function pose(w2c) {
    var c2w = invRigid(w2c);
    return { x: [c2w[0], c2w[4], c2w[8]], y: [c2w[1], c2w[5], c2w[9]], z: [c2w[2], c2w[6], c2w[10]],
             c: [c2w[3], c2w[7], c2w[11]] };
  }
  function fromPose(p) {
    var c2w = [p.x[0], p.y[0], p.z[0], p.c[0], p.x[1], p.y[1], p.z[1], p.c[1], p.x[2], p.y[2], p.z[2], p.c[2],
               0, 0, 0, 1];
    return invRigid(c2w);
  }
  function sub(a, b) { return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]; }
  function add(a, b) { return [a[0] + b[0], a[1] + b[1], a[2] + b[2]]; }
  function scale(a, s) { return [a[0] * s, a[1] * s, a[2] * s]; }

  // -- the viewer: two canvases sharing one camera ----------------------------------------
  function Viewer(box) {
    this.box = box;
    this.cfg = JSON.parse(box.querySelector("script.viewer-data").textContent);
    this.mode = this.cfg.mode || "object";
    this.camIndex = 0;
    this.models = {};   // method -> decoded model (or a Promise of it)
    this.sides = [];
    var self = this;
    var cfg = this.cfg;
    this.target = cfg.center.slice();
    this.up = cfg.up.slice();
    ["left", "right"].forEach(function (side) {
      var el = box.querySelector(".viewer-side." + side);
      if (!el) return;
      var s = { el: el, method: cfg[side], canvas: el.querySelector("canvas"), select: el.querySelector("select") };
      s.gpu = new Canvas(s.canvas, cfg.background);
      s.sorters = {};
      if (s.select) {
        s.select.value = s.method;
        s.select.addEventListener("change", function () { s.method = s.select.value; self.show(s); });
      }
      self.sides.push(s);
    });
    this.status = box.querySelector(".viewer-status");
    var camSel = box.querySelector("select.viewer-camera");
    if (camSel) camSel.addEventListener("change", function () { self.setCamera(Number(camSel.value)); });
    Array.prototype.forEach.call(box.querySelectorAll("button[data-mode]"), function (b) {
      b.addEventListener("click", function () { self.setMode(b.getAttribute("data-mode")); });
    });
    var hires = box.querySelector("input.viewer-hires");
    this.hires = !!(hires && hires.checked);
    if (hires) hires.addEventListener("change", function () { self.hires = hires.checked; self.fit(false); self.refresh(); });
    var reset = box.querySelector("button.viewer-reset");
    if (reset) reset.addEventListener("click", function () { self.setCamera(self.camIndex); });
    this.setCamera(0, true);
    this.bindControls();
    this.ready = Promise.all(this.sides.map(function (s) { return self.show(s); })).then(function () {
      box.setAttribute("data-viewer-ready", "1");
      return self;
    }, function (err) {
      self.say("the viewer could not start: " + err.message);
      throw err;
    });
  }

  Viewer.prototype.say = function (text) { if (this.status) this.status.textContent = text; };

  Viewer.prototype.model = function (method) {
    var self = this;
    if (!this.models[method]) {
      var m = this.cfg.models[method];
      this.models[method] = loadScript(m.src).then(function () {
        var b64 = SPLATS[m.key];
        if (!b64) throw new Error(m.src + " did not define the splats of " + method);
        return decode(m.header, bytesOf(b64));
      });
      this.models[method].catch(function (err) { self.say(err.message); });
    }
    return this.models[method];
  };

  Viewer.prototype.show = function (side) {
    var self = this, method = side.method;
    return this.model(method).then(function (model) {
      side.gpu.upload(method, model);
      if (!side.sorters[method]) side.sorters[method] = new Sorter(model);
      return self.refresh();
    });
  };

  // The camera of the canvas: the dataset camera's intrinsics scaled to the canvas size.
  Viewer.prototype.canvasCamera = function (canvas) {
    var cam = this.cfg.cameras[this.camIndex], sx = canvas.width / cam.w, sy = canvas.height / cam.h;
    return { w2c: this.w2c, K: [cam.K[0] * sx, cam.K[1] * sy, cam.K[2] * sx, cam.K[3] * sy] };
  };

  Viewer.prototype.fit = function (exact) {
    var self = this, cam = this.cfg.cameras[this.camIndex];
    this.sides.forEach(function (s) {
      var w, h;
      if (exact) { w = cam.w; h = cam.h; } else {
        // The dataset's own resolution (the training views hold no finer detail; the page
        // scales the canvas up), or the screen's when asked for (slower on a software GPU).
        var css = Math.max(16, Math.round((s.canvas.clientWidth || 400) * (window.devicePixelRatio || 1)));
        w = self.hires ? css : Math.min(css, cam.w);
        h = Math.max(16, Math.round(w * cam.h / cam.w));
      }
      if (s.canvas.width !== w || s.canvas.height !== h) { s.canvas.width = w; s.canvas.height = h; }
      s.canvas.style.aspectRatio = cam.w + " / " + cam.h;
    });
  };

  // Jump to dataset camera `index`; `exact`: the canvas at that camera's own size.
  Viewer.prototype.setCamera = function (index, quiet, exact) {
    this.camIndex = index;
    this.w2c = this.cfg.cameras[index].w2c.slice();
    var sel = this.box.querySelector("select.viewer-camera");
    if (sel) sel.value = String(index);
    this.fit(!!exact);
    if (!quiet) return this.refresh();
  };

  Viewer.prototype.setMode = function (mode) {
    this.mode = mode;
    Array.prototype.forEach.call(this.box.querySelectorAll("button[data-mode]"), function (b) {
      b.setAttribute("aria-pressed", b.getAttribute("data-mode") === mode ? "true" : "false");
    });
    return this.refresh();
  };

  // Sort for the current camera (in the workers), then draw; a newer request supersedes.
  // Redraw for the current camera and mode. One frame at a time: requests that arrive
  // while a frame is sorting are folded into one next frame with the newest state (a drag
  // never queues up sorts, and every frame drawn is the camera as it was when it started).
  // The promise resolves once a frame started after this call has been drawn.
  Viewer.prototype.refresh = function () {
    var self = this, gen = (this.wanted = (this.wanted || 0) + 1);
    this.waiters = this.waiters || [];
    var p = new Promise(function (resolve, reject) { self.waiters.push({ gen: gen, resolve: resolve, reject: reject }); });
    if (!this.looping) this.frame();
    return p;
  };

  Viewer.prototype.frame = function () {
    var self = this, gen = this.wanted;
    var w2c = this.w2c.slice(), mode = this.mode, modeIndex = MODES.indexOf(mode);
    this.looping = true;
    Promise.all(this.sides.map(function (s) {
      var sorter = s.sorters[s.method];
      if (!sorter) return null;
      return sorter.sort(w2c, modeIndex).then(function (order) { return { side: s, order: order, method: s.method }; });
    })).then(function (done) {
      done.forEach(function (d) {
        if (!d || d.method !== d.side.method) return;  // the side switched method meanwhile: next frame
        d.side.gpu.setOrder(d.order);
        d.side.gpu.draw(d.side.method, self.canvasCamera(d.side.canvas), mode);
      });
      self.frames = (self.frames || 0) + 1;
      self.drawnW2c = w2c;
      self.say(self.describe());
      self.waiters = self.waiters.filter(function (w) { if (w.gen <= gen) { w.resolve(true); return false; } return true; });
      if (self.wanted > gen) self.frame(); else self.looping = false;
    }).catch(function (err) {
      self.looping = false;
      self.say("drawing failed: " + err.message);
      var ws = self.waiters;
      self.waiters = [];
      ws.forEach(function (w) { w.reject(err); });
    });
  };

  Viewer.prototype.describe = function () {
    var self = this;
    return this.sides.map(function (s) {
      var m = self.cfg.models[s.method];
      return s.method + ": " + s.gpu.count.toLocaleString() + " of " + m.header.count.toLocaleString() + " Gaussians drawn";
    }).join(" · ");
  };

  // Camera moves (all keep the camera looking the way it looked, about `target`)
  Viewer.prototype.orbit = function (dx, dy) {
    var p = pose(this.w2c), t = this.target;
    var R = rotAxis(this.up, -dx * 0.008);
    var R2 = rotAxis(mul3v(R, p.x), -dy * 0.008);
    var rot = function (v) { return mul3v(R2, mul3v(R, v)); };
    p.c = add(t, rot(sub(p.c, t)));
    p.x = rot(p.x); p.y = rot(p.y); p.z = rot(p.z);
    this.w2c = fromPose(p);
    return this.refresh();
  };
  Viewer.prototype.pan = function (dx, dy) {
    var p = pose(this.w2c), cam = this.cfg.cameras[this.camIndex];
    var dist = Math.hypot.apply(null, sub(this.target, p.c));
    var w = this.sides.length ? this.sides[0].canvas.clientWidth || cam.w : cam.w;
    var k = dist / (cam.K[0] * w / cam.w);
    var move = add(scale(p.x, -dx * k), scale(p.y, -dy * k));
    p.c = add(p.c, move);
    this.target = add(this.target, move);
    this.w2c = fromPose(p);
    return this.refresh();
  };
  Viewer.prototype.zoom = function (factor) {
    var p = pose(this.w2c);
    p.c = add(this.target, scale(sub(p.c, this.target), factor));
    this.w2c = fromPose(p);
    return this.refresh();
  };

  Viewer.prototype.bindControls = function () {
    var self = this, pointers = {};
    this.sides.forEach(function (s) {
      var c = s.canvas;
      c.style.touchAction = "none";
      c.addEventListener("pointerdown", function (e) {
        c.setPointerCapture(e.pointerId);
        pointers[e.pointerId] = { x: e.clientX, y: e.clientY, button: e.button, shift: e.shiftKey };
      });
      c.addEventListener("pointermove", function (e) {
        var p = pointers[e.pointerId];
        if (!p) return;
        var ids = Object.keys(pointers);
        var dx = e.clientX - p.x, dy = e.clientY - p.y;
        if (ids.length === 2) {  // two fingers: pinch zooms, moving together pans
          var other = pointers[ids[0] == e.pointerId ? ids[1] : ids[0]];
          var before = Math.hypot(p.x - other.x, p.y - other.y);
          var after = Math.hypot(e.clientX - other.x, e.clientY - other.y);
          if (before > 0 && after > 0) self.zoom(before / after);
          self.pan(dx / 2, dy / 2);
        } else if (p.button === 2 || p.button === 1 || p.shift) {
          self.pan(dx, dy);
        } else {
          self.orbit(dx, dy);
        }
        p.x = e.clientX; p.y = e.clientY;
      });
      var up = function (e) { delete pointers[e.pointerId]; };
      c.addEventListener("pointerup", up);
      c.addEventListener("pointercancel", up);
      c.addEventListener("contextmenu", function (e) { e.preventDefault(); });
      c.addEventListener("wheel", function (e) {
        e.preventDefault();
        self.zoom(Math.exp(Math.max(-1, Math.min(1, e.deltaY * 0.002))));
      }, { passive: false });
    });
  };

  // For tests and benchmarks: draw at the dataset camera's own resolution (what
  // cobgs.rasterize renders for it) and return the canvas as a PNG data URL.
  Viewer.prototype.snapshot = function (index, sideIndex) {
    var self = this;
    return this.setCamera(index, false, true).then(function () {
      return self.sides[sideIndex || 0].canvas.toDataURL("image/png");
    });
  };
  // Frames per second of camera moves: each frame orbits a little, sorts and draws, and
  // waits for the GPU (a 1-pixel read) before the next.
  Viewer.prototype.measureFps = function (frames) {
    var self = this, i = 0, t0 = performance.now(), px = new Uint8Array(4);
    function step() {
      if (i++ >= frames) return Promise.resolve(frames / ((performance.now() - t0) / 1000));
      return self.orbit(6, 0).then(function () {
        self.sides.forEach(function (s) { s.gpu.gl.readPixels(0, 0, 1, 1, s.gpu.gl.RGBA, s.gpu.gl.UNSIGNED_BYTE, px); });
        return step();
      });
    }
    return step();
  };

  // -- page -------------------------------------------------------------------------------
  var viewers = (window.cobgsViewers = []);
  function start(box) {
    if (box.cobgsViewer) return box.cobgsViewer.ready;
    try {
      var v = new Viewer(box);
      box.cobgsViewer = v;
      viewers.push(v);
      return v.ready;
    } catch (err) {
      var st = box.querySelector(".viewer-status");
      if (st) st.textContent = "the viewer could not start: " + err.message;
      box.setAttribute("data-viewer-error", err.message);
      return Promise.reject(err);
    }
  }
  window.cobgsStartViewer = start;

  function init() {
    Array.prototype.forEach.call(document.querySelectorAll("details.viewer"), function (d) {
      var box = d.querySelector(".viewer-box");
      d.addEventListener("toggle", function () { if (d.open) start(box).catch(function () {}); });
      if (d.open) start(box).catch(function () {});
    });
  }
  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();
