// Zoom and pan over a board's measured map (dpsa-web, tiles.rs): the tiles of the pyramid
// level whose pixels are closest to the screen's, placed in one layer; the calls (links the
// page carries with their place on the map's finest pixels, data-u and data-v) moved with it.
// Drag to pan; the wheel, + and - to zoom; "whole board" to fit.
(function () {
  'use strict';
  var root = document.getElementById('mapview');
  if (!root) {
    return;
  }
  var frame = document.getElementById('mapframe');
  var status = document.getElementById('map-status');
  var at = document.getElementById('map-at');
  var scaleText = document.getElementById('map-scale');
  var layer = document.createElement('div');
  layer.className = 'maptiles';
  frame.insertBefore(layer, frame.firstChild);
  var calls = Array.prototype.slice.call(frame.querySelectorAll('a.mapcall'));
  var info = null;
  // The view: screen px per finest map px, and the finest px at the frame's top left.
  var scale = 1;
  var minScale = 1;
  var MAX_SCALE = 16;
  var ox = 0;
  var oy = 0;
  var tiles = new Map();
  var failed = 0;

  function say(text) {
    status.textContent = text;
  }

  fetch(root.dataset.map, { credentials: 'same-origin' })
    .then(function (r) {
      if (!r.ok) {
        return r.text().then(function (t) {
          throw new Error(t || r.status + ' ' + r.statusText);
        });
      }
      return r.json();
    })
    .then(function (j) {
      info = j;
      root.dataset.levels = String(j.levels);
      drawBar();
      fit();
      say('');
    })
    .catch(function (e) {
      root.dataset.error = e.message;
      say('The map could not be loaded: ' + e.message);
    });

  function finest() {
    return info.levels - 1;
  }

  // The coarsest level whose pixel is at most one screen pixel (the finest when zoomed in).
  function level() {
    var z = finest() - Math.floor(Math.log2(1 / scale) + 1e-9);
    return Math.max(0, Math.min(finest(), z));
  }

  function clampView() {
    var w = frame.clientWidth / scale;
    var h = frame.clientHeight / scale;
    // Keep some of the map in the frame: its centre may go to the frame's edges.
    ox = Math.max(-w / 2, Math.min(info.width - w / 2, ox));
    oy = Math.max(-h / 2, Math.min(info.height - h / 2, oy));
  }

  function fit() {
    minScale = Math.min(frame.clientWidth / info.width, frame.clientHeight / info.height);
    scale = minScale;
    ox = (info.width - frame.clientWidth / scale) / 2;
    oy = (info.height - frame.clientHeight / scale) / 2;
    render();
  }

  // Zoom by `k` about the frame's point (fx, fy).
  function zoom(k, fx, fy) {
    if (!info) {
      return;
    }
    var s = Math.max(minScale / 2, Math.min(MAX_SCALE, scale * k));
    var u = ox + fx / scale;
    var v = oy + fy / scale;
    scale = s;
    ox = u - fx / scale;
    oy = v - fy / scale;
    render();
  }

  function render() {
    clampView();
    var z = level();
    var f = Math.pow(2, finest() - z);
    var span = info.tile * f;
    var nx = Math.ceil(Math.ceil(info.width / f) / info.tile);
    var ny = Math.ceil(Math.ceil(info.height / f) / info.tile);
    var W = frame.clientWidth;
    var H = frame.clientHeight;
    var x0 = Math.max(0, Math.floor(ox / span));
    var x1 = Math.min(nx - 1, Math.floor((ox + W / scale) / span));
    var y0 = Math.max(0, Math.floor(oy / span));
    var y1 = Math.min(ny - 1, Math.floor((oy + H / scale) / span));
    var want = new Set();
    for (var tx = x0; tx <= x1; tx++) {
      for (var ty = y0; ty <= y1; ty++) {
        var key = z + '/' + tx + '/' + ty;
        want.add(key);
        var img = tiles.get(key);
        if (!img) {
          img = new Image();
          img.className = 'tile';
          img.alt = '';
          img.draggable = false;
          img.dataset.z = String(z);
          img.addEventListener('error', onTileError);
          img.src = root.dataset.tiles + key + '.png';
          layer.appendChild(img);
          tiles.set(key, img);
        }
        // Whole screen pixels, one pixel over, so no seam shows between tiles.
        var left = Math.floor((tx * span - ox) * scale);
        var top = Math.floor((ty * span - oy) * scale);
        img.style.left = left + 'px';
        img.style.top = top + 'px';
        img.style.width = Math.ceil(span * scale) + 1 + 'px';
        img.style.height = Math.ceil(span * scale) + 1 + 'px';
      }
    }
    tiles.forEach(function (img, key) {
      if (!want.has(key)) {
        img.remove();
        tiles.delete(key);
      }
    });
    layer.classList.toggle('pixels', scale > 1.5);
    root.dataset.level = String(z);
    calls.forEach(function (a) {
      var x = (Number(a.dataset.u) - ox) * scale;
      var y = (Number(a.dataset.v) - oy) * scale;
      var inside = x >= 0 && y >= 0 && x <= W && y <= H;
      a.hidden = !inside;
      a.style.left = x + 'px';
      a.style.top = y + 'px';
    });
    declutter();
    showScale();
  }

  // A call's name only where it overlaps no name placed before it (failures first: the page
  // lists them last); every ring stays, and its name is its tooltip.
  function declutter() {
    var placed = [];
    for (var i = calls.length - 1; i >= 0; i--) {
      var a = calls[i];
      var span = a.firstElementChild;
      if (a.hidden || !span) {
        continue;
      }
      a.classList.remove('nolabel');
      var x = parseFloat(a.style.left) + 9;
      var y = parseFloat(a.style.top) - 15;
      var box = [x, y, x + span.offsetWidth, y + span.offsetHeight];
      var clash = placed.some(function (b) {
        return box[0] < b[2] && b[0] < box[2] && box[1] < b[3] && b[1] < box[3];
      });
      if (clash) {
        a.classList.add('nolabel');
      } else {
        placed.push(box);
      }
    }
  }

  function onTileError() {
    failed += 1;
    root.dataset.failedTiles = String(failed);
    say(failed + ' tile(s) could not be loaded');
  }

  // A round length near 120 screen px.
  function showScale() {
    var mm = (120 / scale) * info.pitch_mm;
    var p = Math.pow(10, Math.floor(Math.log10(mm)));
    var nice = [1, 2, 5, 10].map(function (k) {
      return k * p;
    }).filter(function (v) {
      return v <= mm;
    }).pop() || p;
    var px = (nice / info.pitch_mm) * scale;
    scaleText.textContent = (nice >= 1 ? nice : nice.toPrecision(1)) + ' mm';
    scaleText.style.borderBottomWidth = '3px';
    scaleText.style.width = Math.round(px) + 'px';
  }

  // The colour bar: the ramp over the scale, its ends and round values marked in um.
  function drawBar() {
    var c = document.getElementById('mapbar');
    var g = c.getContext('2d');
    var lo = info.range_um[0];
    var hi = info.range_um[1];
    var x0 = 10;
    var w = c.width - 110;
    var grad = g.createLinearGradient(x0, 0, x0 + w, 0);
    info.ramp.forEach(function (rgb, i) {
      grad.addColorStop(i / (info.ramp.length - 1), 'rgb(' + rgb.join(',') + ')');
    });
    g.clearRect(0, 0, c.width, c.height);
    g.fillStyle = grad;
    g.fillRect(x0, 4, w, 14);
    g.fillStyle = 'rgb(' + info.invalid.join(',') + ')';
    g.fillRect(x0 + w + 14, 4, 14, 14);
    g.fillStyle = '#1f2328';
    g.font = '12px sans-serif';
    g.textBaseline = 'top';
    g.fillText('no height', x0 + w + 32, 5);
    var step = Math.pow(10, Math.floor(Math.log10((hi - lo) / 4)));
    [1, 2, 5].some(function (k) {
      if ((hi - lo) / (k * step) <= 6) {
        step = k * step;
        return true;
      }
      return false;
    });
    g.textAlign = 'center';
    for (var v = Math.ceil(lo / step) * step; v <= hi; v += step) {
      var x = x0 + ((v - lo) / (hi - lo)) * w;
      g.fillRect(Math.round(x), 18, 1, 5);
      g.fillText(String(Math.round(v)), x, 25);
    }
    g.textAlign = 'left';
    g.fillText('um', x0 + w + 14, 25);
  }

  // Panning.
  var drag = null;
  frame.addEventListener('pointerdown', function (e) {
    if (!info || e.button !== 0 || e.target.closest('a')) {
      return;
    }
    drag = { x: e.clientX, y: e.clientY, ox: ox, oy: oy };
    frame.setPointerCapture(e.pointerId);
    frame.classList.add('dragging');
  });
  frame.addEventListener('pointermove', function (e) {
    if (!info) {
      return;
    }
    var r = frame.getBoundingClientRect();
    var u = ox + (e.clientX - r.left) / scale;
    var v = oy + (e.clientY - r.top) / scale;
    if (u >= 0 && v >= 0 && u < info.width && v < info.height) {
      at.textContent = 'x ' + (info.x0_mm + u * info.pitch_mm).toFixed(2) + ' mm, y ' +
        (info.y_top_mm - v * info.pitch_mm).toFixed(2) + ' mm';
    } else {
      at.textContent = '';
    }
    if (drag) {
      ox = drag.ox - (e.clientX - drag.x) / scale;
      oy = drag.oy - (e.clientY - drag.y) / scale;
      render();
    }
  });
  function endDrag() {
    drag = null;
    frame.classList.remove('dragging');
  }
  frame.addEventListener('pointerup', endDrag);
  frame.addEventListener('pointercancel', endDrag);
  frame.addEventListener('wheel', function (e) {
    if (!info) {
      return;
    }
    e.preventDefault();
    var r = frame.getBoundingClientRect();
    zoom(Math.pow(1.0015, -e.deltaY), e.clientX - r.left, e.clientY - r.top);
  }, { passive: false });
  document.getElementById('map-in').addEventListener('click', function () {
    zoom(2, frame.clientWidth / 2, frame.clientHeight / 2);
  });
  document.getElementById('map-out').addEventListener('click', function () {
    zoom(0.5, frame.clientWidth / 2, frame.clientHeight / 2);
  });
  document.getElementById('map-fit').addEventListener('click', function () {
    if (info) {
      fit();
    }
  });
  window.addEventListener('resize', function () {
    if (info) {
      render();
    }
  });
})();
