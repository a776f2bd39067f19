/* apo report viewer (schema apo.report/1): draws the embedded task with plotly.js.
 * Static: the page's data is the JSON in #apo-data, written by apo.report.html.
 * Lengths are in the task's units; poses are rows x y z qw qx qy qz of G in E. */
(function () {
  'use strict';

  var errorsBox = document.getElementById('errors');
  function showError(msg) {
    errorsBox.hidden = false;
    errorsBox.textContent += msg + '\n';
  }
  window.addEventListener('error', function (ev) { showError('error: ' + ev.message); });

  var D = JSON.parse(document.getElementById('apo-data').textContent);
  var T = D.task;
  var U = T.units;
  var KINDS = ['M', 'D', 'C', 'SM', 'SD', 'SC'];
  var KIND_COLORS = { M: '#4c9be8', D: '#f2a541', C: '#d9534f', SM: '#a6cdf5', SD: '#f9d29d',
                      SC: '#eea6a4' };
  var PALETTE = ['#1f77b4', '#ff7f0e', '#2ca02c', '#9467bd', '#8c564b', '#e377c2', '#17becf',
                 '#bcbd22', '#d62728', '#7f7f7f'];
  var FREE_COLOR = '#8fa3b8';
  var PLOT_CONFIG = { displaylogo: false, responsive: true,
                      toImageButtonOptions: { format: 'png', scale: 2 } };

  // ------------------------------------------------------------------ data
  function unpack(p) {
    if (!p) { return null; }
    var bin = atob(p.b64);
    var buf = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) { buf[i] = bin.charCodeAt(i); }
    var Ctor = { f4: Float32Array, f8: Float64Array, u1: Uint8Array, u2: Uint16Array,
                 u4: Uint32Array, i4: Int32Array }[p.dtype];
    return new Ctor(buf.buffer);
  }
  function fmt(v, nd) {
    if (v === null || v === undefined || (typeof v === 'number' && !isFinite(v))) { return '–'; }
    return Number(v).toFixed(nd === undefined ? 2 : nd);
  }
  function esc(s) {
    return String(s).replace(/[&<>"']/g, function (c) {
      return { '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;', "'": '&#39;' }[c];
    });
  }
  function vec(v, nd) { return '(' + v.map(function (x) { return fmt(x, nd); }).join(', ') + ')'; }

  var states = T.states;
  var stateIndex = {};
  states.forEach(function (s, i) { stateIndex[s.id] = i; });

  // colour of a contact state: states with the same contacts (same_as) share one
  var stateColor = [];
  (function () {
    var root = {};
    var next = 0;
    states.forEach(function (s, i) {
      var r = s.same_as && stateIndex[s.same_as] !== undefined ? root[s.same_as] : null;
      if (r === null || r === undefined) {
        r = s.elements.length ? PALETTE[next++ % PALETTE.length] : FREE_COLOR;
      }
      root[s.id] = r;
      stateColor[i] = r;
    });
  })();

  var F = D.frames;
  var frame = unpack(F.frame);
  var ftime = unpack(F.t);
  var fstate = unpack(F.state);
  var fobs = unpack(F.observed);
  var fcor = unpack(F.corrected);
  var fresB = unpack(F.residual_before);
  var fresA = unpack(F.residual_after);
  var fconv = unpack(F.converged);
  var frep = unpack(F.repaired);

  function statePoseRow(i) {
    var p = states[i].pose;
    return [p.position[0], p.position[1], p.position[2],
            p.quaternion[0], p.quaternion[1], p.quaternion[2], p.quaternion[3]];
  }
  function row(arr, i) { return arr ? Array.prototype.slice.call(arr, 7 * i, 7 * i + 7) : null; }

  // tracks: the demonstration, then planned motion / simulated execution
  var tracks = [{
    name: 'demonstration', kind: 'demonstration', n: frame.length, t: ftime,
    pose: function (i) { return row(fcor || fobs, i) || statePoseRow(fstate[i]); },
    ghost: function (i) {
      if (fcor && fobs) { return row(fobs, i); }
      if (!fcor && fobs) { return statePoseRow(fstate[i]); }
      return null;
    },
    ghostName: fcor && fobs ? 'grasped, observed pose' : 'state\u2019s corrected pose',
    solidName: fcor ? 'grasped, corrected pose' : (fobs ? 'grasped, observed pose'
                                                       : 'grasped, state pose'),
    state: function (i) { return fstate[i]; },
    label: function (i) { return 'state ' + states[fstate[i]].id; }
  }];
  D.tracks.forEach(function (tr) {
    var tt = unpack(tr.t);
    var pose = unpack(tr.pose);
    var lab = unpack(tr.label);
    var per = unpack(tr.state);  // per-sample state index (65535: none), where given
    tracks.push({
      name: tr.name, kind: tr.kind, note: tr.note, n: tt.length, t: tt,
      pose: function (i) { return row(pose, i); },
      ghost: function () { return null; },
      solidName: 'grasped, ' + tr.name, ghostName: '',
      state: function (i) {
        if (per) { return per[i] === 65535 ? null : per[i]; }
        var sid = tr.label_states ? tr.label_states[lab[i]] : null;
        var k = sid === null || sid === undefined ? undefined : stateIndex[sid];
        return k === undefined ? null : k;
      },
      label: function (i) { return tr.labels[lab[i]]; },
      raw: pose
    });
  });

  // ------------------------------------------------------------------ geometry
  function rotation(q) {
    var w = q[0], x = q[1], y = q[2], z = q[3];
    return [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]];
  }
  function apply(R, t, p) {
    return [R[0][0] * p[0] + R[0][1] * p[1] + R[0][2] * p[2] + t[0],
            R[1][0] * p[0] + R[1][1] * p[1] + R[1][2] * p[2] + t[1],
            R[2][0] * p[0] + R[2][1] * p[1] + R[2][2] * p[2] + t[2]];
  }
  function applyT(R, t, p) {  // inverse pose applied to p
    var d = [p[0] - t[0], p[1] - t[1], p[2] - t[2]];
    return [R[0][0] * d[0] + R[1][0] * d[1] + R[2][0] * d[2],
            R[0][1] * d[0] + R[1][1] * d[1] + R[2][1] * d[2],
            R[0][2] * d[0] + R[1][2] * d[1] + R[2][2] * d[2]];
  }
  function mesh(m) {
    if (!m) { return null; }
    return { name: m.name, V: unpack(m.vertices), T: unpack(m.triangles),
             E: unpack(m.edges), scale: m.scale };
  }
  var G = mesh(D.models.grasped);
  var E = mesh(D.models.environment);
  function posed(m, poseRow) {
    var n = m.V.length / 3;
    var x = new Array(n), y = new Array(n), z = new Array(n);
    var R = poseRow ? rotation(poseRow.slice(3)) : null;
    for (var v = 0; v < n; v++) {
      var p = [m.V[3 * v], m.V[3 * v + 1], m.V[3 * v + 2]];
      if (R) { p = apply(R, poseRow, p); }
      x[v] = p[0]; y[v] = p[1]; z[v] = p[2];
    }
    return { x: x, y: y, z: z };
  }
  function edgeLines(m, P) {
    var x = [], y = [], z = [];
    for (var e = 0; e < m.E.length; e += 2) {
      var a = m.E[e], b = m.E[e + 1];
      x.push(P.x[a], P.x[b], null); y.push(P.y[a], P.y[b], null); z.push(P.z[a], P.z[b], null);
    }
    return { x: x, y: y, z: z };
  }
  function triIdx(m) {
    var i = [], j = [], k = [];
    for (var t = 0; t < m.T.length; t += 3) { i.push(m.T[t]); j.push(m.T[t + 1]); k.push(m.T[t + 2]); }
    return { i: i, j: j, k: k };
  }
  var Gtri = G ? triIdx(G) : null;
  var Etri = E ? triIdx(E) : null;
  var EP = E ? posed(E, null) : null;
  var EE = E ? edgeLines(E, EP) : null;  // static: built once, same arrays every redraw
  var sceneScale = Math.min(G ? G.scale : Infinity, E ? E.scale : Infinity);
  if (!isFinite(sceneScale)) { sceneScale = 20 * (T.threshold || 1); }
  var normalLen = 0.14 * sceneScale;

  // contacts of state si shown at pose poseRow: grasped vertices move with G, environment
  // vertices stay; normals of G's faces/edges (FV, EV) turn with G (docs/report.md)
  function contactsAt(si, poseRow) {
    var s = states[si];
    var rep = statePoseRow(si);
    var Rr = rotation(rep.slice(3));
    var Rn = poseRow ? rotation(poseRow.slice(3)) : Rr;
    var tn = poseRow || rep;
    var out = [];
    s.elements.forEach(function (el) {
      var withG = el.grasped[0] === 'v' || el.kind === 'EE';
      var p = withG ? apply(Rn, tn, applyT(Rr, rep, el.point)) : el.point.slice();
      var turn = el.kind === 'FV' || el.kind === 'EV';
      var ns = el.normals.map(function (n) {
        return turn ? apply(Rn, [0, 0, 0], applyT(Rr, [0, 0, 0], n)) : n;
      });
      out.push({ el: el, p: p, normals: ns });
    });
    return out;
  }
  function elementLabel(el) {
    return el.kind + ' ' + el.grasped[0] + el.grasped[1] + '-' + el.environment[0] + el.environment[1];
  }

  // ------------------------------------------------------------------ state of the page
  var cur = { track: 0, i: 0 };
  var slider = document.getElementById('slider');
  var show = { ghost: true, normals: true, paths: true, envClear: true };

  function trackPath(tr) {
    var x = [], y = [], z = [];
    for (var i = 0; i < tr.n; i++) { var p = tr.pose(i); x.push(p[0]); y.push(p[1]); z.push(p[2]); }
    return { x: x, y: y, z: z };
  }
  var paths = tracks.map(trackPath);
  var TRACK_COLORS = ['#6b7785', '#1565c0', '#ef6c00', '#2e7d32'];

  function sceneTraces() {
    var tr = tracks[cur.track];
    var pose = tr.pose(cur.i);
    var si = tr.state(cur.i);
    var col = si === null ? '#607d8b' : stateColor[si];
    var data = [];
    var lighting = { ambient: 0.55, diffuse: 0.7, specular: 0.15, roughness: 0.6 };
    if (E) {
      data.push({ type: 'mesh3d', name: 'environment: ' + E.name, x: EP.x, y: EP.y, z: EP.z,
                  i: Etri.i, j: Etri.j, k: Etri.k, color: '#b0b7c0',
                  opacity: show.envClear ? 0.35 : 1, flatshading: true, lighting: lighting,
                  hoverinfo: 'name', showlegend: true });
      data.push({ type: 'scatter3d', mode: 'lines', name: 'environment edges', x: EE.x, y: EE.y,
                  z: EE.z, line: { color: '#4a5360', width: 2 }, hoverinfo: 'skip',
                  showlegend: false });
    }
    if (G) {
      var GP = posed(G, pose);
      data.push({ type: 'mesh3d', name: tr.solidName, x: GP.x, y: GP.y, z: GP.z,
                  i: Gtri.i, j: Gtri.j, k: Gtri.k, color: col, opacity: 1, flatshading: true,
                  lighting: lighting, hoverinfo: 'name', showlegend: true });
      var ge = edgeLines(G, GP);
      data.push({ type: 'scatter3d', mode: 'lines', name: 'grasped edges', x: ge.x, y: ge.y,
                  z: ge.z, line: { color: '#222', width: 2 }, hoverinfo: 'skip', showlegend: false });
      var gh = tr.ghost(cur.i);
      if (gh && show.ghost) {
        var ghe = edgeLines(G, posed(G, gh));
        data.push({ type: 'scatter3d', mode: 'lines', name: tr.ghostName, x: ghe.x, y: ghe.y,
                    z: ghe.z, line: { color: '#e53935', width: 3, dash: 'dash' },
                    hoverinfo: 'name' });
      }
    }
    if (show.normals && si !== null) {
      var cs = contactsAt(si, pose);
      var groups = [[], []];
      cs.forEach(function (c) { groups[c.el.normals.length > 1 ? 1 : 0].push(c); });
      var lx = [], ly = [], lz = [], cx = [], cy = [], cz = [], cu = [], cv = [], cw = [];
      groups.forEach(function (g, singular) {
        data.push({ type: 'scatter3d', mode: 'markers',
                    name: singular ? 'singular contact element' : 'contact point',
                    x: g.map(function (c) { return c.p[0]; }),
                    y: g.map(function (c) { return c.p[1]; }),
                    z: g.map(function (c) { return c.p[2]; }),
                    text: g.map(function (c) {
                      return elementLabel(c.el) + (singular ? ' (singular, ' + c.normals.length +
                        ' normals)' : '') + '<br>point ' + vec(c.p, 2) + ' ' + U;
                    }),
                    hoverinfo: 'text',
                    marker: singular ? { size: 7, color: '#d81b60', symbol: 'diamond',
                                         line: { color: '#000', width: 1 } }
                                     : { size: 4, color: '#111', symbol: 'circle' } });
        g.forEach(function (c) {
          c.normals.forEach(function (n) {
            var q = [c.p[0] + normalLen * n[0], c.p[1] + normalLen * n[1], c.p[2] + normalLen * n[2]];
            lx.push(c.p[0], q[0], null); ly.push(c.p[1], q[1], null); lz.push(c.p[2], q[2], null);
            cx.push(q[0]); cy.push(q[1]); cz.push(q[2]);
            cu.push(0.3 * normalLen * n[0]); cv.push(0.3 * normalLen * n[1]);
            cw.push(0.3 * normalLen * n[2]);
          });
        });
      });
      data.push({ type: 'scatter3d', mode: 'lines', name: 'separating normal (E \u2192 G)',
                  x: lx, y: ly, z: lz, line: { color: '#2e7d32', width: 4 }, hoverinfo: 'skip' });
      if (cx.length) {
        data.push({ type: 'cone', name: 'normal heads', x: cx, y: cy, z: cz, u: cu, v: cv, w: cw,
                    anchor: 'tip', sizemode: 'raw', sizeref: 1,
                    colorscale: [[0, '#2e7d32'], [1, '#2e7d32']], showscale: false,
                    hoverinfo: 'skip', showlegend: false });
      }
    }
    if (show.paths) {
      tracks.forEach(function (t, k) {
        data.push({ type: 'scatter3d', mode: 'lines', name: 'path: ' + t.name,
                    x: paths[k].x, y: paths[k].y, z: paths[k].z,
                    line: { color: TRACK_COLORS[k % TRACK_COLORS.length], width: k === cur.track ? 4 : 2,
                            dash: t.kind === 'planned' ? 'dash' : 'solid' },
                    hoverinfo: 'name' });
      });
      data.push({ type: 'scatter3d', mode: 'markers', name: 'now', x: [pose[0]], y: [pose[1]],
                  z: [pose[2]], marker: { size: 5, color: '#000' }, hoverinfo: 'skip',
                  showlegend: false });
    }
    return data;
  }
  var sceneLayout = {
    margin: { l: 0, r: 0, t: 0, b: 0 }, uirevision: 'keep', showlegend: true,
    legend: { x: 0, y: 1, bgcolor: 'rgba(255,255,255,0.75)', font: { size: 11 } },
    scene: { aspectmode: 'data', uirevision: 'keep',
             xaxis: { title: { text: 'x [' + U + ']' } }, yaxis: { title: { text: 'y [' + U + ']' } },
             zaxis: { title: { text: 'z [' + U + ']' } },
             camera: { eye: { x: 1.5, y: -1.6, z: 1.1 }, up: { x: 0, y: 0, z: 1 } } }
  };

  // ------------------------------------------------------------------ DOF timeline
  var frameStep = (function () {
    var n = ftime.length;
    if (n < 2) { return 1; }
    var d = (ftime[n - 1] - ftime[0]) / (frame[n - 1] - frame[0] || 1);
    return d > 0 ? d : 1;
  })();
  function stateSpan(i) {
    var a = states[i].times[0];
    var b = i + 1 < states.length ? states[i + 1].times[0] : states[i].times[1] + frameStep;
    return [a, b];
  }
  function timelineFigure() {
    var data = [];
    var mids = [], widths = [], hover = [];
    states.forEach(function (s, i) {
      var sp = stateSpan(i);
      mids.push(0.5 * (sp[0] + sp[1])); widths.push(sp[1] - sp[0]);
      hover.push('state ' + s.id + (s.singular ? ' (singular)' : '') + '<br>frames ' +
                 s.frames[0] + '–' + s.frames[1]);
    });
    ['translation', 'rotation'].forEach(function (space, r) {
      var ax = r === 0 ? '' : '2';
      KINDS.forEach(function (k, j) {
        data.push({ type: 'bar', x: mids, width: widths, name: k,
                    y: states.map(function (s) { return s.six[space][j]; }),
                    xaxis: 'x' + ax, yaxis: 'y' + ax, legendgroup: k, showlegend: r === 0,
                    marker: { color: KIND_COLORS[k], line: { width: 0 } },
                    customdata: states.map(function (s, i) { return i; }),
                    hovertemplate: '%{text}<br>' + space + ' ' + k + ' = %{y}<extra></extra>',
                    text: hover, textposition: 'none' });
      });
      var xs = [], ys = [];
      states.forEach(function (s, i) {
        var sp = stateSpan(i);
        xs.push(sp[0], sp[1]); ys.push(s.fig25[6 + r], s.fig25[6 + r]);
      });
      data.push({ type: 'scatter', mode: 'lines', x: xs, y: ys, name: 'restraining',
                  xaxis: 'x' + ax, yaxis: 'y' + ax, legendgroup: 'restraining', showlegend: r === 0,
                  line: { color: '#000', width: 2, dash: 'dot' },
                  hovertemplate: space + ' restraining = %{y}<extra></extra>' });
    });
    var shapes = [];
    var ann = [];
    T.transitions.forEach(function (t) {
      var s = states[stateIndex[t.to]];
      var x = s.times[0];
      var c = t.critical ? '#c62828' : (t.direct ? '#555' : '#ef6c00');
      shapes.push({ type: 'line', xref: 'x', yref: 'paper', x0: x, x1: x, y0: 0, y1: 1,
                    line: { color: c, width: t.critical ? 2.5 : 0.8, dash: t.direct ? 'solid' : 'dash' } });
      if (t.critical) {
        ann.push({ x: x, y: -0.02, xref: 'x', yref: 'paper', text: 'critical', showarrow: false,
                   font: { color: '#c62828', size: 10 }, yanchor: 'top' });
      }
    });
    var span = stateSpan(states.length - 1)[1] - states[0].times[0];
    states.forEach(function (s, i) {
      var sp = stateSpan(i);
      if (states.length > 40 && (sp[1] - sp[0]) < span / 80) { return; }
      ann.push({ x: 0.5 * (sp[0] + sp[1]), y: 1.0, xref: 'x', yref: 'paper', text: '<b>' + s.id + '</b>',
                 showarrow: false, yanchor: 'bottom', font: { size: 12, color: stateColor[i] } });
    });
    shapes.push({ type: 'line', xref: 'x', yref: 'paper', x0: ftime[0], x1: ftime[0], y0: 0, y1: 1.06,
                  line: { color: '#000', width: 2 }, name: 'cursor' });
    var layout = {
      barmode: 'stack', bargap: 0, margin: { l: 60, r: 10, t: 28, b: 46 }, hovermode: 'closest',
      legend: { orientation: 'h', y: -0.2, x: 0 },
      xaxis: { anchor: 'y', domain: [0, 1], showticklabels: false, matches: 'x2' },
      yaxis: { domain: [0.54, 1], range: [0, 3.05], dtick: 1, title: { text: 'translation DOF' } },
      xaxis2: { anchor: 'y2', domain: [0, 1], title: { text: 'time [s]' } },
      yaxis2: { domain: [0, 0.46], range: [0, 3.05], dtick: 1, title: { text: 'rotation DOF' } },
      shapes: shapes, annotations: ann
    };
    return { data: data, layout: layout };
  }

  // ------------------------------------------------------------------ state graph
  var DIR_NAMES = ['x', 'y', 'z'];
  function dirText(d) {
    var n = Math.hypot(d[0], d[1], d[2]);
    if (!(n > 0)) { return ''; }
    for (var a = 0; a < 3; a++) {
      if (Math.abs(d[a]) / n > 0.995) { return (d[a] > 0 ? '+' : '\u2212') + DIR_NAMES[a]; }
    }
    return '(' + d.map(function (v) { return fmt(v / n, 2); }).join(',') + ')';
  }
  function subskillText(k, oneLine) {
    var name = { push_to: 'push-to', release: 'release', slide: 'slide' }[k.kind] || k.kind;
    var sp = k.space === 'translation' ? 'T' : 'R';
    var ty = k.type ? '(' + k.type + ')' : '';
    var d = dirText(k.direction);
    var sep = d.length > 3 && !oneLine ? '<br>' : ' ';
    var dir = d ? sep + (k.space === 'translation' ? 'along ' : 'about ') + d : '';
    return name + ' ' + sp + ty + dir;
  }
  function eightText(s) {
    var f = s.fig25;
    var S = s.singular ? 'S ' : '';
    return 'T ' + S + f[0] + ' ' + f[1] + ' ' + f[2] + '  R ' + S + f[3] + ' ' + f[4] + ' ' + f[5] +
           '<br>r<sub>T</sub> ' + f[6] + '  r<sub>R</sub> ' + f[7];
  }
  var graphNodes = [];
  var GW = 1.5, GH = 0.95;  // node size in the graph's units
  function currentBox(W, H) {  // the frame drawn around the current state's box (moved by update)
    return { type: 'rect', x0: -W / 2 - 0.08, x1: W / 2 + 0.08, y0: -H / 2 - 0.08, y1: H / 2 + 0.08,
             line: { color: '#000', width: 3 }, fillcolor: 'rgba(0,0,0,0)', name: 'current' };
  }
  function hoverTargets(hx, hy, htext, hidx) {  // invisible markers over the boxes: hover and click
    return [{ type: 'scatter', mode: 'markers', x: hx, y: hy, text: htext, customdata: hidx,
              hoverinfo: 'text', marker: { size: 40, opacity: 0 }, showlegend: false }];
  }
  function graphFigure() {
    var n = states.length;
    var cols = Math.min(n, 5);
    var rejShown = T.rejected.slice().sort(function (a, b) {
      return (b.frames[1] - b.frames[0]) - (a.frames[1] - a.frames[0]);
    }).slice(0, 12);
    var dy = rejShown.length ? 3.3 : 2.0;
    var W = GW, H = GH, DX = 3.3;
    var shapes = [], ann = [];
    var hx = [], hy = [], htext = [], hidx = [];
    graphNodes = [];
    states.forEach(function (s, i) {
      var r = Math.floor(i / cols), c = i % cols;
      if (r % 2 === 1) { c = cols - 1 - c; }
      var x = c * DX, y = -r * dy;
      graphNodes.push([x, y]);
      shapes.push({ type: 'rect', x0: x - W / 2, x1: x + W / 2, y0: y - H / 2, y1: y + H / 2,
                    fillcolor: stateColor[i], opacity: 1, layer: 'below',
                    line: { color: '#222', width: 1, dash: s.singular ? 'dot' : 'solid' } });
      ann.push({ x: x, y: y, text: '<b>' + s.id + '</b>' + (s.singular ? ' (singular)' : '') +
                 (s.same_as ? ' = ' + s.same_as : '') + '<br>' + eightText(s),
                 showarrow: false, font: { size: 11, color: '#fff' }, align: 'center' });
      hx.push(x); hy.push(y); hidx.push(i);
      htext.push('state ' + s.id + '<br>frames ' + s.frames[0] + '–' + s.frames[1] + '<br>' +
                 s.elements.length + ' contact element(s)' + (s.pose_converged ? '' : '<br>pose not corrected'));
    });
    T.transitions.forEach(function (t, k) {
      var a = graphNodes[stateIndex[t.from]], b = graphNodes[stateIndex[t.to]];
      var horiz = Math.abs(a[1] - b[1]) < 1e-9;
      var sx = horiz ? Math.sign(b[0] - a[0]) * W / 2 : 0, sy = horiz ? 0 : -H / 2;
      var ex = horiz ? -Math.sign(b[0] - a[0]) * W / 2 : 0, ey = horiz ? 0 : H / 2;
      var col = t.critical ? '#c62828' : (t.direct ? '#333' : '#ef6c00');
      ann.push({ x: b[0] + ex, y: b[1] + ey, ax: a[0] + sx, ay: a[1] + sy, xref: 'x', yref: 'y',
                 axref: 'x', ayref: 'y', text: '', showarrow: true, arrowhead: 2, arrowsize: 1.2,
                 arrowwidth: t.critical ? 3 : 1.5, arrowcolor: col });
      var lines = t.subskills.map(subskillText);
      if (!lines.length) { lines = ['(no sub-skill)']; }
      if (t.critical) { lines.unshift('<b>CRITICAL</b>'); }
      if (!t.direct) { lines.unshift('<b>not direct</b>'); }
      var mx = 0.5 * (a[0] + sx + b[0] + ex), my = 0.5 * (a[1] + sy + b[1] + ey);
      ann.push({ x: horiz ? mx : mx + 0.15, y: horiz ? my + 0.12 : my, text: '(' + (k + 1) + ') ' + lines.join('<br>'),
                 showarrow: false, yanchor: horiz ? 'bottom' : 'middle', xanchor: horiz ? 'center' : 'left',
                 font: { size: 10, color: col } });
    });
    var perState = {};
    var placed = 0;
    rejShown.forEach(function (rj) {
      var to = rj.replaced_by.length ? stateIndex[rj.replaced_by[0]] : 0;
      if (to === undefined) { to = 0; }
      var slot = perState[to] = (perState[to] || 0) + 1;
      if (slot > 2) { return; }  // two per state fit under its box; the table has all
      placed += 1;
      var base = graphNodes[to];
      var x = base[0] + (slot - 1) * 1.45 - 0.7, y = base[1] - 1.3;
      var w = 1.35, h = 0.7;
      shapes.push({ type: 'rect', x0: x - w / 2, x1: x + w / 2, y0: y - h / 2, y1: y + h / 2,
                    fillcolor: '#eceff1', line: { color: '#9e9e9e', width: 1, dash: 'dot' } });
      shapes.push({ type: 'line', x0: x - w / 2, x1: x + w / 2, y0: y - h / 2, y1: y + h / 2,
                    line: { color: '#c62828', width: 1.5 } });
      shapes.push({ type: 'line', x0: x - w / 2, x1: x + w / 2, y0: y + h / 2, y1: y - h / 2,
                    line: { color: '#c62828', width: 1.5 } });
      shapes.push({ type: 'line', x0: x, x1: base[0], y0: y + h / 2, y1: base[1] - H / 2,
                    line: { color: '#9e9e9e', width: 1, dash: 'dot' } });
      var reason = rj.reason.length > 44 ? rj.reason.slice(0, 43) + '\u2026' : rj.reason;
      var cut = reason.lastIndexOf(' ', 24);
      if (reason.length > 24 && cut > 8) { reason = reason.slice(0, cut) + '\n' + reason.slice(cut + 1); }
      ann.push({ x: x, y: y, text: '<b>frames ' + rj.frames[0] + '–' + rj.frames[1] + '</b><br>' +
                 esc(reason).replace('\n', '<br>'), showarrow: false, font: { size: 9, color: '#222' },
                 bgcolor: 'rgba(255,255,255,0.6)' });
      hx.push(x); hy.push(y); hidx.push(-1);
      htext.push('rejected run, frames ' + rj.frames[0] + '–' + rj.frames[1] + '<br>' +
                 esc(rj.elements.join(', ')) + '<br>replaced by ' + rj.replaced_by.join(', ') +
                 '<br>reason: ' + esc(rj.reason));
    });
    if (T.rejected.length > placed) {
      ann.push({ xref: 'paper', yref: 'paper', x: 1, y: 0, xanchor: 'right', yanchor: 'top',
                 showarrow: false, font: { size: 10, color: '#666' },
                 text: (T.rejected.length - placed) + ' more rejected run(s): see the table' });
    }
    shapes.push(currentBox(W, H));
    var rows = Math.ceil(n / cols);
    var data = hoverTargets(hx, hy, htext, hidx);
    var layout = {
      margin: { l: 10, r: 10, t: 10, b: 10 }, showlegend: false, hovermode: 'closest',
      xaxis: { visible: false, range: [-W, (cols - 1) * DX + W + (rejShown.length ? 0.8 : 0)] },
      yaxis: { visible: false, range: [-(rows - 1) * dy - (rejShown.length ? 1.7 : H), H],
               scaleanchor: 'x', scaleratio: 1 },
      shapes: shapes, annotations: ann, dragmode: 'pan'
    };
    var height = Math.max(260, 130 + rows * (rejShown.length ? 190 : 130));
    return { data: data, layout: layout, height: height };
  }

  // the distinct-state graph (task.json "graph"): each contact state once, transitions counted
  function boxExit(c, d, W, H) {  // point where the ray from box centre c along d leaves it
    var sx = Math.abs(d[0]) > 1e-12 ? (W / 2) / Math.abs(d[0]) : Infinity;
    var sy = Math.abs(d[1]) > 1e-12 ? (H / 2) / Math.abs(d[1]) : Infinity;
    var k = Math.min(sx, sy);
    return [c[0] + k * d[0], c[1] + k * d[1]];
  }
  function distinctGraphFigure() {
    var Gr = T.graph;
    var m = Gr.states.length;
    var cols = Math.min(m, 5);
    var W = GW, H = GH, DX = 3.3, DY = 2.4;
    var shapes = [], ann = [];
    var hx = [], hy = [], htext = [], hidx = [];
    var nodeOf = {}, pos = [];
    Gr.states.forEach(function (g, i) {
      var r = Math.floor(i / cols), c = i % cols;
      if (r % 2 === 1) { c = cols - 1 - c; }
      var x = c * DX, y = -r * DY;
      pos.push([x, y]);
      g.states.forEach(function (sid) { nodeOf[sid] = i; });
      var k = stateIndex[g.id], s = states[k];
      shapes.push({ type: 'rect', x0: x - W / 2, x1: x + W / 2, y0: y - H / 2, y1: y + H / 2,
                    fillcolor: stateColor[k], layer: 'below',
                    line: { color: '#222', width: 1, dash: s.singular ? 'dot' : 'solid' } });
      ann.push({ x: x, y: y, showarrow: false, font: { size: 11, color: '#fff' }, align: 'center',
                 text: '<b>' + g.id + '</b>' + (g.states.length > 1 ? ' \u00d7' + g.states.length : '') +
                       (s.singular ? ' (singular)' : '') + '<br>' + eightText(s) });
      hx.push(x); hy.push(y); hidx.push(k);
      htext.push('contact state ' + g.id + '<br>visits: ' + g.states.map(function (sid, j) {
        return sid + ' (frames ' + g.visits[j][0] + '–' + g.visits[j][1] + ')';
      }).join(', '));
    });
    var pairs = {};
    Gr.transitions.forEach(function (t) { pairs[t.from + '>' + t.to] = true; });
    Gr.transitions.forEach(function (t, k) {
      var a = pos[nodeOf[t.from]], b = pos[nodeOf[t.to]];
      var d = [b[0] - a[0], b[1] - a[1]], L = Math.hypot(d[0], d[1]) || 1;
      d = [d[0] / L, d[1] / L];
      var off = pairs[t.to + '>' + t.from] ? 0.16 : 0;  // a pair both ways: two parallel arrows
      var o = [-d[1] * off, d[0] * off];
      var p0 = boxExit(a, d, W, H), p1 = boxExit(b, [-d[0], -d[1]], W, H);
      p0 = [p0[0] + o[0], p0[1] + o[1]]; p1 = [p1[0] + o[0], p1[1] + o[1]];
      var col = t.critical ? '#c62828' : (t.direct ? '#333' : '#ef6c00');
      ann.push({ x: p1[0], y: p1[1], ax: p0[0], ay: p0[1], xref: 'x', yref: 'y', axref: 'x', ayref: 'y',
                 text: '', showarrow: true, arrowhead: 2, arrowsize: 1.2,
                 arrowwidth: t.critical ? 3 : 1.5, arrowcolor: col });
      var first = null;
      T.transitions.forEach(function (u) { if (first === null && u.frame === t.frames[0]) { first = u; } });
      var lines = first ? first.subskills.map(function (u) { return subskillText(u); }) : [];
      if (!lines.length) { lines = ['(no sub-skill)']; }
      if (t.critical) { lines.unshift('<b>CRITICAL</b>'); }
      if (!t.direct) { lines.unshift('<b>not direct</b>'); }
      var mx = 0.5 * (p0[0] + p1[0]) + 2.2 * o[0], my = 0.5 * (p0[1] + p1[1]) + 2.2 * o[1];
      ann.push({ x: mx, y: my, showarrow: false, font: { size: 10, color: col },
                 bgcolor: 'rgba(255,255,255,0.75)',
                 text: '(' + (k + 1) + ')' + (t.count > 1 ? ' \u00d7' + t.count : '') + ' ' + lines.join('<br>') });
    });
    graphNodes = states.map(function (s) { return pos[nodeOf[s.id]]; });
    shapes.push(currentBox(W, H));
    var rows = Math.ceil(m / cols);
    var data = hoverTargets(hx, hy, htext, hidx);
    var layout = {
      margin: { l: 10, r: 10, t: 10, b: 10 }, showlegend: false, hovermode: 'closest',
      xaxis: { visible: false, range: [-W, (cols - 1) * DX + W] },
      yaxis: { visible: false, range: [-(rows - 1) * DY - H, H], scaleanchor: 'x', scaleratio: 1 },
      shapes: shapes, annotations: ann, dragmode: 'pan'
    };
    return { data: data, layout: layout, height: Math.max(260, 130 + rows * 160) };
  }
  var graphMode = T.graph && T.graph.states.length < states.length ? 'distinct' : 'visits';
  function currentGraphFigure() { return graphMode === 'distinct' ? distinctGraphFigure() : graphFigure(); }

  // ------------------------------------------------------------------ tables and panels
  function table(head, rows, opts) {
    var h = '<table class="data"><thead><tr>' + head.map(function (c) { return '<th>' + c + '</th>'; }).join('') +
            '</tr></thead><tbody>';
    rows.forEach(function (r, i) {
      var attrs = opts && opts.rowAttrs ? opts.rowAttrs(i) : '';
      h += '<tr ' + attrs + '>' + r.map(function (c) { return '<td>' + c + '</td>'; }).join('') + '</tr>';
    });
    return h + '</tbody></table>';
  }
  function dofList(list) {
    return list.length ? list.map(function (p) { return p[0] + '\u2192' + p[1]; }).join(', ') : '–';
  }
  function fillTables() {
    document.getElementById('states-table').innerHTML = table(
      ['state', 'frames', 'time [s]', 'T: M D C', 'R: M D C', 'r<sub>T</sub> r<sub>R</sub>', 'elements',
       'position [' + U + ']', 'quaternion (w x y z)', 'notes'],
      states.map(function (s, i) {
        var f = s.fig25, S = s.singular ? '<span class="sing">S</span> ' : '';
        var notes = [];
        if (s.singular) { notes.push('<span class="sing">singular</span>'); }
        if (!s.pose_converged) { notes.push('pose not corrected'); }
        if (s.same_as) { notes.push('= ' + s.same_as); }
        return ['<span class="letter" style="background:' + stateColor[i] + '">' + s.id + '</span>',
                s.frames[0] + '–' + s.frames[1], fmt(s.times[0], 3) + '–' + fmt(s.times[1], 3),
                S + f[0] + ' ' + f[1] + ' ' + f[2], S + f[3] + ' ' + f[4] + ' ' + f[5], f[6] + ' ' + f[7],
                s.elements.length, vec(s.pose.position, 2), vec(s.pose.quaternion, 4), notes.join(', ')];
      }),
      { rowAttrs: function (i) { return 'class="clickable" data-state="' + i + '"'; } });
    document.getElementById('transitions-table').innerHTML = table(
      ['#', 'transition', 'frame', 'DOF transitions T', 'DOF transitions R', 'sub-skills', 'critical',
       'direct', 'decomposition'],
      T.transitions.map(function (t, k) {
        var sk = t.subskills.map(function (u) {
          return esc(subskillText(u, true)) + (u.point ? ' through ' + vec(u.point, 2) + ' ' + U : '') +
                 ' <span class="muted">[' + esc(u.source) + ']</span>';
        }).join('<br>') || '–';
        var dec = t.decomposition ? ['translation', 'rotation'].map(function (sp) {
          return sp[0].toUpperCase() + ': ' + esc(t.decomposition[sp].choice);
        }).join(', ') : '';
        return [k + 1, t.from + ' \u2192 ' + t.to, t.frame, dofList(t.dof_transitions.translation),
                dofList(t.dof_transitions.rotation), sk,
                t.critical ? '<span class="crit">CRITICAL</span>' : '', t.direct ? 'yes' : '<b>no</b>', dec];
      }),
      { rowAttrs: function (k) {
        return 'class="clickable" data-state="' + stateIndex[T.transitions[k].to] + '"'; } });
    document.getElementById('rejected-table').innerHTML = T.rejected.length ? table(
      ['frames', 'observed elements', 'replaced by', 'reason'],
      T.rejected.map(function (r) {
        return [r.frames[0] + '–' + r.frames[1], esc(r.elements.join(', ')) || '(no contact)',
                r.replaced_by.join(', '), esc(r.reason)];
      })) : '<p class="muted">none: every observed run of frames was kept.</p>';
    Array.prototype.forEach.call(document.querySelectorAll('tr.clickable'), function (tr) {
      tr.addEventListener('click', function () { seekState(Number(tr.dataset.state)); });
    });
  }
  function fillInputs() {
    var I = D.inputs || {};
    var h = '';
    var kv = [['source', esc(T.source || '–')], ['units', esc(U)], ['frame', esc(T.frame)],
              ['contact threshold', fmt(T.threshold, 4) + ' ' + esc(U)],
              ['frames', T.n_frames + (F.n_frames !== frame.length ? ' (replay shows ' + frame.length + ')' : '')],
              ['per-frame data', esc(F.source) + (fcor ? ', corrected poses' : '') + (fobs ? ', observed poses' : '')],
              ['noise estimate', I.noise === null || I.noise === undefined ? 'not recorded' :
                                 esc(typeof I.noise === 'object' ? JSON.stringify(I.noise) : I.noise)],
              ['apo version', esc(D.apo_version)], ['report written', esc(I.written || '–')]];
    kv.forEach(function (p) { h += '<div class="kv"><b>' + p[0] + '</b> ' + p[1] + '</div>'; });
    ['grasped', 'environment'].forEach(function (r) {
      var m = T.models[r];
      h += '<div class="kv"><b>' + r + ' model</b> <code>' + esc(m.path) + '</code> ' +
           '<span class="muted">SHA-256 ' + esc(m.sha256 || 'none') + '</span></div>';
    });
    if (I.files && I.files.length) {
      h += '<h3>Files</h3>' + table(['role', 'path', 'bytes', 'SHA-256', 'status'], I.files.map(function (f) {
        var st = f.status === 'ok' ? 'ok' : '<span class="crit">' + esc(f.status) + '</span>';
        return [esc(f.role), '<code>' + esc(f.path) + '</code>', f.bytes === null ? '–' : f.bytes,
                '<code>' + esc(f.sha256 || '–') + '</code>', st];
      }));
    }
    if (I.extra && Object.keys(I.extra).length) {
      h += '<h3>extra (task.json)</h3><pre class="mono">' + esc(JSON.stringify(I.extra, null, 1)) + '</pre>';
    }
    tracks.slice(1).forEach(function (t) {
      h += '<div class="kv"><b>' + esc(t.name) + '</b> ' + t.n + ' samples, ' +
           fmt(t.t[t.n - 1] - t.t[0], 2) + ' s' + (t.note ? ': ' + esc(t.note) : '') + '</div>';
    });
    document.getElementById('inputs-body').innerHTML = h;
  }
  function fillNow() {
    var tr = tracks[cur.track];
    var i = cur.i;
    var si = tr.state(i);
    var letter = document.getElementById('cur-state');
    var det = document.getElementById('cur-detail');
    var demo = cur.track === 0;
    var head = demo ? 'frame ' + frame[i] + ' of ' + F.n_frames + ', t = ' + fmt(tr.t[i], 3) + ' s'
                    : tr.name + ': sample ' + (i + 1) + ' of ' + tr.n + ', t = ' + fmt(tr.t[i], 3) + ' s, ' + tr.label(i);
    document.getElementById('cur-frame').textContent = head;
    if (si === null) {
      letter.textContent = '–'; letter.style.background = '#607d8b';
      det.innerHTML = '<p>' + esc(tr.label(i)) + '</p>';
      return;
    }
    var s = states[si];
    letter.textContent = s.id; letter.style.background = stateColor[si];
    var prefix = demo ? '' : '<div class="kv"><b>primitive</b> ' + esc(tr.label(i)) + '</div>' +
                 '<div class="kv muted">' + (tr.kind === 'executed' ? 'contact state the simulation is in'
                                           : 'state the primitive starts from') + '</div>';
    var f = s.fig25, S = s.singular ? 'S' : '';
    var h = '<table class="eight" id="cur-fig25"><tr><th colspan="3">translation ' + S + '</th>' +
            '<th colspan="3">rotation ' + S + '</th><th colspan="2">restraining</th></tr>' +
            '<tr><th>' + S + 'M</th><th>' + S + 'D</th><th>' + S + 'C</th><th>' + S + 'M</th><th>' + S +
            'D</th><th>' + S + 'C</th><th>T</th><th>R</th></tr><tr>' +
            f.map(function (v) { return '<td>' + v + '</td>'; }).join('') + '</tr></table>';
    h += '<div class="kv"><b>six (T)</b> M D C SM SD SC = ' + s.six.translation.join(' ') + '</div>';
    h += '<div class="kv"><b>six (R)</b> M D C SM SD SC = ' + s.six.rotation.join(' ') + '</div>';
    h += '<div class="kv"><b>frames</b> ' + s.frames[0] + '–' + s.frames[1] + ' (' + fmt(s.times[0], 3) + '–' +
         fmt(s.times[1], 3) + ' s)' + (s.singular ? ' <span class="sing">singular state</span>' : '') + '</div>';
    if (demo) {
      if (fresB) { h += '<div class="kv"><b>residual before</b> ' + fmt(fresB[i], 4) + ' ' + U + '</div>'; }
      if (fresA) { h += '<div class="kv"><b>residual after</b> ' + fmt(fresA[i], 6) + ' ' + U + '</div>'; }
      if (fconv) { h += '<div class="kv"><b>correction</b> ' + (fconv[i] ? 'converged' : '<span class="crit">failed</span>') + '</div>'; }
      if (frep && frep[i]) { h += '<div class="kv"><b>repaired</b> observed state replaced</div>'; }
    }
    var k = stateIndex[s.id];
    if (k > 0) {
      var tin = T.transitions[k - 1];
      h += '<div class="kv"><b>entered by</b> ' + (tin.critical ? '<span class="crit">critical</span> ' : '') +
           (tin.subskills.map(function (u) { return subskillText(u, true); }).join(', ') || 'no sub-skill') + '</div>';
    }
    h += '<div class="kv"><b>contact elements</b> ' + s.elements.length + '</div><ul class="elements">';
    s.elements.forEach(function (el) {
      var sing = el.normals.length > 1;
      h += '<li' + (sing ? ' class="sing"' : '') + '><code>' + elementLabel(el) + '</code> at ' + vec(el.point, 2) +
           ', ' + el.normals.length + ' normal' + (sing ? 's (singular)' : '') + '</li>';
    });
    h += '</ul>';
    det.innerHTML = prefix + h;
  }
  function highlightState(si) {
    Array.prototype.forEach.call(document.querySelectorAll('#states-table tr.clickable'), function (r) {
      r.classList.toggle('current', Number(r.dataset.state) === si);
    });
  }

  // ------------------------------------------------------------------ drawing and linking
  var view3d = document.getElementById('view3d');
  var timeline = document.getElementById('timeline');
  var graph = document.getElementById('graph');
  var timelineCursor = 0, graphCursor = 0;
  var drawing = false, pending = false;
  function draw3d() {
    if (drawing) { pending = true; return Promise.resolve(); }
    drawing = true;
    return Plotly.react(view3d, sceneTraces(), sceneLayout, PLOT_CONFIG).then(function () {
      drawing = false;
      if (pending) { pending = false; return draw3d(); }
    });
  }
  function update() {
    fillNow();
    var tr = tracks[cur.track];
    var si = tr.state(cur.i);
    var t = tr.t[cur.i];
    if (cur.track === 0) {
      Plotly.relayout(timeline, (function () {
        var u = {};
        u['shapes[' + timelineCursor + '].x0'] = t; u['shapes[' + timelineCursor + '].x1'] = t;
        return u;
      })());
    }
    if (si !== null) {
      var p = graphNodes[si];
      var u = {};
      var W = GW, H = GH;
      u['shapes[' + graphCursor + '].x0'] = p[0] - W / 2 - 0.08; u['shapes[' + graphCursor + '].x1'] = p[0] + W / 2 + 0.08;
      u['shapes[' + graphCursor + '].y0'] = p[1] - H / 2 - 0.08; u['shapes[' + graphCursor + '].y1'] = p[1] + H / 2 + 0.08;
      Plotly.relayout(graph, u);
      highlightState(si);
    }
    document.body.dataset.state = si === null ? '' : states[si].id;
    document.body.dataset.frame = cur.track === 0 ? String(frame[cur.i]) : String(cur.i);
    return draw3d();
  }
  function seek(i) {
    var n = tracks[cur.track].n;
    cur.i = Math.max(0, Math.min(n - 1, i | 0));
    slider.value = String(cur.i);
    return update();
  }
  function nearestIndex(t, times) {
    var lo = 0, hi = times.length - 1;
    while (lo < hi) { var mid = (lo + hi) >> 1; if (times[mid] < t) { lo = mid + 1; } else { hi = mid; } }
    if (lo > 0 && Math.abs(times[lo - 1] - t) <= Math.abs(times[lo] - t)) { lo -= 1; }
    return lo;
  }
  function seekState(si) {
    if (cur.track !== 0) { setTrack(0); }
    var first = states[si].frames[0];
    var idx = 0;
    while (idx < frame.length - 1 && frame[idx] < first) { idx++; }
    return seek(idx);
  }
  function setTrack(k) {
    cur.track = k;
    document.getElementById('track').value = String(k);
    slider.max = String(tracks[k].n - 1);
    return seek(0);
  }

  var playing = false, lastStamp = null, playTime = 0;
  var playBtn = document.getElementById('play');
  function step(stamp) {
    if (!playing) { return; }
    var tr = tracks[cur.track];
    if (lastStamp !== null) {
      playTime += (stamp - lastStamp) / 1000 * Number(document.getElementById('speed').value);
    }
    lastStamp = stamp;
    var i = nearestIndex(playTime, tr.t);
    if (i !== cur.i) { seek(i); }
    if (playTime >= tr.t[tr.n - 1]) { setPlaying(false); return; }
    requestAnimationFrame(step);
  }
  function setPlaying(on) {
    playing = on;
    playBtn.innerHTML = on ? '&#10074;&#10074; pause' : '&#9654; play';
    if (on) {
      var tr = tracks[cur.track];
      if (cur.i >= tr.n - 1) { cur.i = 0; }
      playTime = tr.t[cur.i]; lastStamp = null;
      requestAnimationFrame(step);
    }
  }

  function init() {
    document.getElementById('title').textContent = 'apo report: ' + (T.source || 'demonstration');
    var crit = T.transitions.filter(function (t) { return t.critical; }).length;
    document.getElementById('summary').textContent =
      T.n_frames + ' frames, ' + states.length + ' states (' +
      states.filter(function (s) { return s.singular; }).length + ' singular), ' +
      T.transitions.length + ' transitions (' + crit + ' critical), ' + T.rejected.length +
      ' rejected run(s); models: ' + T.models.grasped.name + ' in ' + T.models.environment.name +
      '; lengths in ' + U + ', environment frame.';
    if (D.notes && D.notes.length) {
      var nb = document.getElementById('notes');
      nb.hidden = false;
      nb.innerHTML = D.notes.map(esc).join('<br>');
    }
    var sel = document.getElementById('track');
    tracks.forEach(function (t, k) {
      var o = document.createElement('option');
      o.value = String(k); o.textContent = t.name; sel.appendChild(o);
    });
    sel.addEventListener('change', function () { setPlaying(false); setTrack(Number(sel.value)); });
    slider.max = String(tracks[0].n - 1);
    slider.addEventListener('input', function () { seek(Number(slider.value)); });
    playBtn.addEventListener('click', function () { setPlaying(!playing); });
    document.addEventListener('keydown', function (ev) {
      if (ev.key === ' ' && ev.target === document.body) { ev.preventDefault(); setPlaying(!playing); }
    });
    [['show-ghost', 'ghost'], ['show-normals', 'normals'], ['show-paths', 'paths'],
     ['env-clear', 'envClear']].forEach(function (p) {
      var box = document.getElementById(p[0]);
      box.addEventListener('change', function () { show[p[1]] = box.checked; draw3d(); });
    });
    fillTables();
    fillInputs();
    var tl = timelineFigure();
    timelineCursor = tl.layout.shapes.length - 1;
    var gr = currentGraphFigure();
    graphCursor = gr.layout.shapes.length - 1;
    var modeSel = document.getElementById('graph-mode');
    if (!T.graph) { modeSel.hidden = true; }
    modeSel.value = graphMode;
    modeSel.addEventListener('change', function () {
      graphMode = modeSel.value;
      var g2 = currentGraphFigure();
      graphCursor = g2.layout.shapes.length - 1;
      graph.style.height = g2.height + 'px';
      Plotly.react(graph, g2.data, g2.layout, PLOT_CONFIG).then(function () { update(); });
    });
    graph.style.height = gr.height + 'px';
    var jobs = [
      Plotly.newPlot(view3d, sceneTraces(), sceneLayout, PLOT_CONFIG),
      Plotly.newPlot(timeline, tl.data, tl.layout, PLOT_CONFIG),
      Plotly.newPlot(graph, gr.data, gr.layout, PLOT_CONFIG)
    ];
    Promise.all(jobs).then(function () {
      timeline.on('plotly_click', function (ev) {
        var pt = ev.points && ev.points[0];
        if (pt && pt.customdata !== undefined) { seekState(pt.customdata); }
      });
      graph.on('plotly_click', function (ev) {
        var pt = ev.points && ev.points[0];
        if (pt && pt.customdata >= 0) { seekState(pt.customdata); }
      });
      // the plots were drawn at frame 0: fill the panels without drawing the 3D view again
      fillNow();
      highlightState(tracks[0].state(0));
      document.body.dataset.state = states[tracks[0].state(0)].id;
      document.body.dataset.frame = String(frame[0]);
    }).then(function () {
      window.apoReady = performance.now();
      document.body.dataset.ready = '1';
    }).catch(function (e) { showError('drawing failed: ' + e); console.error(e); });
  }
  window.apo = { data: D, seek: seek, seekState: seekState, setTrack: setTrack,
                 current: function () { return { track: cur.track, index: cur.i }; } };
  init();
})();
