// Animated 3-D skeleton of the report: a rotating orthographic view on a <canvas>, play/pause and a
// frame slider. Data: the JSON in <script id="skeleton-data"> (see pipeline/report.py, _viewer_data):
// {frames: [...], fps, estimate: series, truth: series or null}, where a series is
// {bones: [[i, j], ...], sides: ["l"|"r"|"c" per joint], poses: [[[x, y, z] per joint] or null per frame]};
// metres, world frame, +z up.
(function () {
  "use strict";
  const data = JSON.parse(document.getElementById("skeleton-data").textContent);
  const canvas = document.getElementById("skeleton-canvas");
  const context = canvas.getContext("2d");
  const playButton = document.getElementById("skeleton-play");
  const slider = document.getElementById("skeleton-frame");
  const label = document.getElementById("skeleton-label");
  const colours = { l: "#0080ff", r: "#ff2020", c: "#00a000" };
  const ELEVATION = 0.3;  // radians the view looks down, so the floor grid reads as a plane
  const count = data.frames.length;

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
  const scale = 0.8 * Math.min(canvas.width, canvas.height) / (extent * 1.2);

  let frame = 0, azimuth = 0.6, playing = true, last = null;
  slider.max = String(Math.max(count - 1, 0));

  function project(p) {
    // Turn about the vertical axis by the azimuth, look down by a fixed elevation, drop depth
    // (orthographic); +z is up on screen.
    const x = p[0] - centre[0], y = p[1] - centre[1], z = p[2] - centre[2];
    const u = Math.cos(azimuth) * x - Math.sin(azimuth) * y;
    const depth = Math.sin(azimuth) * x + Math.cos(azimuth) * y;
    const up = Math.cos(ELEVATION) * z + Math.sin(ELEVATION) * depth;
    return [canvas.width / 2 + scale * u, canvas.height / 2 - scale * up];
  }

  function drawPose(series, pose, colourOf, width) {
    context.lineWidth = width;
    for (const [i, j] of series.bones) {
      const a = project(pose[i]), b = project(pose[j]);
      context.strokeStyle = colourOf(j);
      context.beginPath(); context.moveTo(a[0], a[1]); context.lineTo(b[0], b[1]); context.stroke();
    }
  }

  function drawFloor() {
    context.strokeStyle = "#dddddd"; context.lineWidth = 1;
    const floor = Math.min(lo[2], 0), half = extent;
    for (let k = -4; k <= 4; k++) {
      const s = (k / 4) * half;
      for (const [a, b] of [[[centre[0] + s, centre[1] - half, floor], [centre[0] + s, centre[1] + half, floor]],
                            [[centre[0] - half, centre[1] + s, floor], [centre[0] + half, centre[1] + s, floor]]]) {
        const pa = project(a), pb = project(b);
        context.beginPath(); context.moveTo(pa[0], pa[1]); context.lineTo(pb[0], pb[1]); context.stroke();
      }
    }
  }

  function draw() {
    context.clearRect(0, 0, canvas.width, canvas.height);
    drawFloor();
    if (data.truth && data.truth.poses[frame]) drawPose(data.truth, data.truth.poses[frame], () => "#999999", 5);
    const pose = data.estimate.poses[frame];
    if (pose) drawPose(data.estimate, pose, (j) => colours[data.estimate.sides[j]], 3);
    label.textContent = "frame " + data.frames[frame] + (pose ? "" : " (not estimated)");
    slider.value = String(frame);
  }

  function tick(time) {
    if (playing) {
      if (last !== null) {
        const seconds = (time - last) / 1000;
        azimuth += 0.5 * seconds;
        frame = (frame + Math.max(1, Math.round(seconds * data.fps))) % count;
      }
      last = time;
      draw();
    }
    window.requestAnimationFrame(tick);
  }

  playButton.addEventListener("click", function () {
    playing = !playing; last = null;
    playButton.textContent = playing ? "pause" : "play";
  });
  slider.addEventListener("input", function () { frame = Number(slider.value); draw(); });

  if (count > 0) {
    draw();
    window.requestAnimationFrame(tick);
  }
  document.getElementById("skeleton-status").textContent = "rendered " + count + " frames";
})();
