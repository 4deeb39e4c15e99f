// dpsa: the pad's kept heights as a lit surface (view3d.rs). The WebGL is dpsa-web's own; the
// matrices come from gl-matrix (npm, bundled into the binary at build time). Drag to turn the
// surface, the wheel to come closer. Sets `data-triangles` on the canvas once drawn, or
// `data-error` with the reason it was not.
(function () {
  'use strict';
  var canvas = document.getElementById('pad3d');
  if (!canvas) {
    return;
  }
  var gl = canvas.getContext('webgl', { preserveDrawingBuffer: true, antialias: true });
  if (!gl || !window.glMatrix) {
    canvas.setAttribute('data-error', gl ? 'gl-matrix missing' : 'no WebGL in this browser');
    return;
  }
  var mat4 = window.glMatrix.mat4;

  // The pages' colour scale (dpsa_formats::images::colour): t in [0, 1].
  var STOPS = [
    [0.19, 0.07, 0.60],
    [0.10, 0.60, 0.90],
    [0.30, 0.85, 0.35],
    [0.98, 0.85, 0.15],
    [0.85, 0.10, 0.10]
  ];
  function colour(t) {
    var x = Math.min(Math.max(t, 0), 1) * (STOPS.length - 1);
    var i = Math.min(Math.floor(x), STOPS.length - 2);
    var f = x - i;
    return [0, 1, 2].map(function (k) {
      return STOPS[i][k] * (1 - f) + STOPS[i + 1][k] * f;
    });
  }

  function shader(type, source) {
    var s = gl.createShader(type);
    gl.shaderSource(s, source);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) {
      throw new Error(gl.getShaderInfoLog(s));
    }
    return s;
  }

  var VERTEX = [
    'attribute vec3 position;',
    'attribute vec3 normal;',
    'attribute vec3 colour;',
    'uniform mat4 projection;',
    'uniform mat4 view;',
    'varying vec3 vNormal;',
    'varying vec3 vColour;',
    'void main() {',
    '  vNormal = normal;',
    '  vColour = colour;',
    '  gl_Position = projection * view * vec4(position, 1.0);',
    '}'
  ].join('\n');
  var FRAGMENT = [
    'precision mediump float;',
    'varying vec3 vNormal;',
    'varying vec3 vColour;',
    'void main() {',
    '  vec3 light = normalize(vec3(-0.4, -0.5, 1.0));',
    '  float lit = 0.45 + 0.55 * max(dot(normalize(vNormal), light), 0.0);',
    '  gl_FragColor = vec4(vColour * lit, 1.0);',
    '}'
  ].join('\n');

  // The mesh of `d` (view3d::json): positions in mm (heights times `ex`), normals, colours
  // and two triangles a cell whose four samples are valid; at most 65536 vertices (16-bit
  // indices: a larger crop is taken every `step`-th sample).
  function mesh(d, ex) {
    var step = Math.max(1, Math.ceil(Math.sqrt((d.nx * d.ny) / 65000)));
    var mx = Math.floor((d.nx - 1) / step) + 1;
    var my = Math.floor((d.ny - 1) / step) + 1;
    var p = d.pitch_mm * step;
    var n = mx * my;
    var pos = new Float32Array(3 * n);
    var nor = new Float32Array(3 * n);
    var col = new Float32Array(3 * n);
    var ok = new Uint8Array(n);
    var z = new Float32Array(n);
    for (var a = 0; a < mx; a++) {
      for (var b = 0; b < my; b++) {
        var v = d.heights[a * step * d.ny + b * step];
        var k = a * my + b;
        ok[k] = v === null ? 0 : 1;
        z[k] = v === null ? 0 : (v / 1000) * ex;
        pos[3 * k] = (a - (mx - 1) / 2) * p;
        pos[3 * k + 1] = (b - (my - 1) / 2) * p;
        pos[3 * k + 2] = z[k];
        var c = v === null ? [0.35, 0.35, 0.35] : colour(v / d.top_um);
        col.set(c, 3 * k);
      }
    }
    for (a = 0; a < mx; a++) {
      for (b = 0; b < my; b++) {
        k = a * my + b;
        var dx = (z[Math.min(a + 1, mx - 1) * my + b] - z[Math.max(a - 1, 0) * my + b]) / (2 * p);
        var dy = (z[a * my + Math.min(b + 1, my - 1)] - z[a * my + Math.max(b - 1, 0)]) / (2 * p);
        var len = Math.sqrt(dx * dx + dy * dy + 1);
        nor.set([-dx / len, -dy / len, 1 / len], 3 * k);
      }
    }
    var idx = [];
    for (a = 0; a + 1 < mx; a++) {
      for (b = 0; b + 1 < my; b++) {
        var q = [a * my + b, (a + 1) * my + b, (a + 1) * my + b + 1, a * my + b + 1];
        if (ok[q[0]] && ok[q[1]] && ok[q[2]] && ok[q[3]]) {
          idx.push(q[0], q[1], q[2], q[0], q[2], q[3]);
        }
      }
    }
    return {
      pos: pos,
      nor: nor,
      col: col,
      idx: new Uint16Array(idx),
      side: Math.max(mx, my) * p
    };
  }

  function start(d, ex) {
    var m = mesh(d, ex);
    var prog = gl.createProgram();
    gl.attachShader(prog, shader(gl.VERTEX_SHADER, VERTEX));
    gl.attachShader(prog, shader(gl.FRAGMENT_SHADER, FRAGMENT));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) {
      throw new Error(gl.getProgramInfoLog(prog));
    }
    gl.useProgram(prog);
    [['position', m.pos], ['normal', m.nor], ['colour', m.col]].forEach(function (a) {
      var buf = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, buf);
      gl.bufferData(gl.ARRAY_BUFFER, a[1], gl.STATIC_DRAW);
      var loc = gl.getAttribLocation(prog, a[0]);
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, 3, gl.FLOAT, false, 0, 0);
    });
    var ib = gl.createBuffer();
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, m.idx, gl.STATIC_DRAW);
    var uProjection = gl.getUniformLocation(prog, 'projection');
    var uView = gl.getUniformLocation(prog, 'view');
    gl.enable(gl.DEPTH_TEST);
    // Seen from the front and above, board x to the right and y away from the viewer.
    var view = { azimuth: -0.45, elevation: 0.75, distance: 1.35 * m.side };
    var projection = mat4.create();
    var eye = mat4.create();
    function draw() {
      gl.viewport(0, 0, canvas.width, canvas.height);
      gl.clearColor(0.97, 0.97, 0.98, 1);
      gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
      mat4.perspective(projection, 0.7, canvas.width / canvas.height, m.side / 100, m.side * 20);
      var ce = Math.cos(view.elevation);
      var at = [
        view.distance * ce * Math.sin(view.azimuth),
        -view.distance * ce * Math.cos(view.azimuth),
        view.distance * Math.sin(view.elevation)
      ];
      mat4.lookAt(eye, at, [0, 0, 0], [0, 0, 1]);
      gl.uniformMatrix4fv(uProjection, false, projection);
      gl.uniformMatrix4fv(uView, false, eye);
      gl.drawElements(gl.TRIANGLES, m.idx.length, gl.UNSIGNED_SHORT, 0);
    }
    draw();
    canvas.setAttribute('data-triangles', String(m.idx.length / 3));
    var drag = null;
    canvas.addEventListener('pointerdown', function (e) {
      drag = [e.clientX, e.clientY];
      canvas.setPointerCapture(e.pointerId);
    });
    canvas.addEventListener('pointerup', function () {
      drag = null;
    });
    canvas.addEventListener('pointermove', function (e) {
      if (!drag) {
        return;
      }
      view.azimuth -= (e.clientX - drag[0]) * 0.01;
      view.elevation = Math.min(1.5, Math.max(0.05, view.elevation + (e.clientY - drag[1]) * 0.01));
      drag = [e.clientX, e.clientY];
      window.requestAnimationFrame(draw);
    });
    canvas.addEventListener('wheel', function (e) {
      e.preventDefault();
      view.distance = Math.min(6 * m.side, Math.max(0.3 * m.side, view.distance * Math.exp(e.deltaY * 0.001)));
      window.requestAnimationFrame(draw);
    }, { passive: false });
  }

  fetch(canvas.getAttribute('data-src'))
    .then(function (r) {
      if (!r.ok) {
        throw new Error('heights.json: ' + r.status);
      }
      return r.json();
    })
    .then(function (d) {
      start(d, Number(canvas.getAttribute('data-exaggeration')) || 1);
    })
    .catch(function (e) {
      canvas.setAttribute('data-error', String(e));
    });
})();
