// 3-D skeleton of the report on a <canvas>: orthographic view, orbit by dragging, zoom with the wheel,
// double-click to reset; play/pause, a frame slider and a playback speed.
// Data: the JSON in <script id="skeleton-data"> (see pipeline/report.py, viewer_data):
// {frames: [...], fps, estimate: series, truth: series or null, categories: [tracker's category or null]},
// where a series is {bones: [[i, j], ...], sides: ["l"|"r"|"c" per joint], poses: [[[x, y, z] per joint] or
// null per frame]}; metres, world frame, +z up.
//
// Playback follows a clock in seconds of capture time, advanced by the time stamps of the animation frames:
// frame number first + clock * fps is shown, whatever the screen's refresh rate (60 or 144 Hz alike), and
// gaps in the frame numbers (lost frames, a frame step) take their real time.
// window.skeletonViewer drives it from outside (tests, a screen recorder): tick(ms), seek(s), play(),
// pause(), detach() (stop following the browser's animation frames), state().
(function () {
  "use strict";
  const data = JSON.parse(document.getElementById("skeleton-data").textContent);
  const canvas = document.getElementById("skeleton-canvas");
  const context = canvas.getContext("2d");
  const playButton = document.getElementById("skeleton-play");
  const slider = document.getElementById("skeleton-frame");
  const speedSelect = document.getElementById("skeleton-speed");
  const label = document.getElementById("skeleton-label");
  const colours = { l: "#0080ff", r: "#ff2020", c: "#00a000" };
  const TRUTH_COLOUR = "#9a9a9a";
  const count = data.frames.length;
  const first = count ? data.frames[0] : 0;
  // One loop lasts from the first frame to one frame past the last, so the last frame shows as long as the others.
  const duration = count ? (data.frames[count - 1] - first + 1) / data.fps : 0;
  const HOME = { azimuth: 0.6, elevation: 0.3, zoom: 1 };

  // Centre and scale from every joint of every frame, so the view does not jump while playing.
  const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  for (const series of [data.estimate, data.truth]) {
    if (!series) continue;
    for (const pose of series.poses) {
      if (!pose) continue;
      for (const p of pose) for (let k = 0; k < 3; k++) { lo[k] = Math.min(lo[k], p[k]); hi[k] = Math.max(hi[k], p[k]); }
    }
  }
  const centre = lo.map((v, k) => (v + hi[k]) / 2);
  const extent = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2], 0.5);
  const baseScale = 0.8 * Math.min(canvas.width, canvas.height) / (extent * 1.2);

  const view = { azimuth: HOME.azimuth, elevation: HOME.elevation, zoom: HOME.zoom };
  let clock = 0, speed = 1, playing = true, last = null, index = 0, following = true;
  slider.max = String(Math.max(count - 1, 0));

  function indexAt(seconds) {
    // The last frame whose number is at most first + seconds * fps (binary search over sorted frames).
    const target = first + seconds * data.fps + 1e-9;
    let low = 0, high = count - 1;
    while (low < high) {
      const middle = (low + high + 1) >> 1;
      if (data.frames[middle] <= target) low = middle; else high = middle - 1;
    }
    return low;
  }

  function project(p) {
    // Turn about the vertical by the azimuth, look down by the elevation, drop depth (orthographic).
    const x = p[0] - centre[0], y = p[1] - centre[1], z = p[2] - centre[2];
    const u = Math.cos(view.azimuth) * x - Math.sin(view.azimuth) * y;
    const depth = Math.sin(view.azimuth) * x + Math.cos(view.azimuth) * y;
    const up = Math.cos(view.elevation) * z + Math.sin(view.elevation) * depth;
    const scale = baseScale * view.zoom;
    return [canvas.width / 2 + scale * u, canvas.height / 2 - scale * up];
  }

  function line(a, b) {
    const pa = project(a), pb = project(b);
    context.beginPath(); context.moveTo(pa[0], pa[1]); context.lineTo(pb[0], pb[1]); context.stroke();
  }

  function drawPose(series, pose, colourOf, width, radius) {
    context.lineWidth = width;
    for (const [i, j] of series.bones) {
      context.strokeStyle = colourOf(j);
      line(pose[i], pose[j]);
    }
    for (let j = 0; j < pose.length; j++) {
      const p = project(pose[j]);
      context.fillStyle = colourOf(j);
      context.beginPath(); context.arc(p[0], p[1], radius, 0, 2 * Math.PI); context.fill();
    }
  }

  function drawFloor() {
    context.strokeStyle = "#dddddd"; context.lineWidth = 1;
    const floor = Math.min(lo[2], 0), half = extent;
    for (let k = -4; k <= 4; k++) {
      const s = (k / 4) * half;
      line([centre[0] + s, centre[1] - half, floor], [centre[0] + s, centre[1] + half, floor]);
      line([centre[0] - half, centre[1] + s, floor], [centre[0] + half, centre[1] + s, floor]);
    }
  }

  function draw() {
    context.clearRect(0, 0, canvas.width, canvas.height);
    drawFloor();
    const truth = data.truth && data.truth.poses[index];
    if (truth) drawPose(data.truth, truth, () => TRUTH_COLOUR, 5, 4);
    const pose = data.estimate.poses[index];
    if (pose) drawPose(data.estimate, pose, (j) => colours[data.estimate.sides[j]], 3, 3.5);
    const category = data.categories ? data.categories[index] : null;
    label.textContent = "frame " + data.frames[index] + " (" + ((data.frames[index] - first) / data.fps).toFixed(2)
      + " s)" + (pose ? (category ? ", " + category : "") : ", not estimated");
    slider.value = String(index);
  }

  function tick(time) {
    // One animation frame at time stamp `time` (ms): the clock moves by the real time since the last one.
    if (playing && last !== null) clock = (clock + speed * (time - last) / 1000) % duration;
    last = playing ? time : null;
    index = indexAt(clock);
    draw();
  }

  function loop(time) {
    if (!following) return;
    tick(time);
    window.requestAnimationFrame(loop);
  }

  function setPlaying(on) {
    playing = on; last = null;
    playButton.textContent = playing ? "pause" : "play";
  }

  function seek(seconds) {
    clock = Math.min(Math.max(seconds, 0), Math.max(duration - 1e-9, 0)); last = null;
    index = indexAt(clock); draw();
  }

  playButton.addEventListener("click", function () { setPlaying(!playing); });
  slider.addEventListener("input", function () {
    setPlaying(false);
    seek((data.frames[Number(slider.value)] - first) / data.fps);
  });
  speedSelect.addEventListener("change", function () { speed = Number(speedSelect.value); last = null; });

  // A drag that starts on the canvas follows the pointer anywhere on the page until it is released.
  let drag = null;
  canvas.addEventListener("pointerdown", function (event) {
    drag = { x: event.clientX, y: event.clientY };
    event.preventDefault();  // no text selection while dragging
  });
  window.addEventListener("pointermove", function (event) {
    if (!drag) return;
    view.azimuth += 0.01 * (event.clientX - drag.x);
    view.elevation = Math.min(Math.max(view.elevation + 0.01 * (event.clientY - drag.y), -1.5), 1.5);
    drag = { x: event.clientX, y: event.clientY };
    draw();
  });
  window.addEventListener("pointerup", function () { drag = null; });
  window.addEventListener("pointercancel", function () { drag = null; });
  canvas.addEventListener("wheel", function (event) {
    event.preventDefault();  // the page would scroll instead
    view.zoom = Math.min(Math.max(view.zoom * Math.exp(-0.0015 * event.deltaY), 0.2), 10);
    draw();
  }, { passive: false });
  canvas.addEventListener("dblclick", function () { Object.assign(view, HOME); draw(); });

  window.skeletonViewer = {
    tick: tick, seek: seek,
    play: function () { setPlaying(true); }, pause: function () { setPlaying(false); },
    detach: function () { following = false; last = null; },
    state: function () {
      return { clock: clock, frame: count ? data.frames[index] : null, index: index, playing: playing,
               fps: data.fps, duration: duration, view: Object.assign({}, view) };
    },
  };

  if (count > 0) {
    draw();
    window.requestAnimationFrame(loop);
  }
  document.getElementById("skeleton-status").textContent = "rendered " + count + " frames";
})();
