// Zoom: every canvas of a group shows the same source pixels (same fractional position), magnified
// without smoothing. body[data-ready] reports whether every <img> decoded, for people and tests.
(function () {
  "use strict";
  const BOX = 160;
  const level = document.getElementById("zoom-level");
  function render(group) {
    const u = Number(group.dataset.u), v = Number(group.dataset.v), zoom = Number(level.value);
    for (const fig of group.querySelectorAll(".fig")) {
      const img = fig.querySelector("img.px"), canvas = fig.querySelector("canvas.zoom");
      const marker = fig.querySelector(".marker");
      const w = img.naturalWidth, h = img.naturalHeight, span = BOX / zoom;
      const x = Math.min(w - 1, Math.floor(u * w)), y = Math.min(h - 1, Math.floor(v * h));
      const ctx = canvas.getContext("2d");
      ctx.imageSmoothingEnabled = false;
      ctx.fillStyle = "#303030";
      ctx.fillRect(0, 0, BOX, BOX);
      ctx.drawImage(img, x + 0.5 - span / 2, y + 0.5 - span / 2, span, span, 0, 0, BOX, BOX);
      canvas.dataset.x = x;
      canvas.dataset.y = y;
      canvas.hidden = false;
      marker.style.left = (100 * (x + 0.5 - span / 2) / w) + "%";
      marker.style.top = (100 * (y + 0.5 - span / 2) / h) + "%";
      marker.style.width = (100 * span / w) + "%";
      marker.style.height = (100 * span / h) + "%";
      marker.hidden = false;
    }
  }
  function hide(group) {
    for (const el of group.querySelectorAll("canvas.zoom, .marker")) el.hidden = true;
  }
  function at(event, group) {
    const r = event.currentTarget.getBoundingClientRect();
    group.dataset.u = Math.min(Math.max((event.clientX - r.left) / r.width, 0), 1);
    group.dataset.v = Math.min(Math.max((event.clientY - r.top) / r.height, 0), 1);
  }
  for (const img of document.querySelectorAll(".fig img.px")) {
    const group = img.closest(".group");
    img.addEventListener("mousemove", (e) => {
      if (!group.classList.contains("pinned")) { at(e, group); render(group); }
    });
    img.addEventListener("mouseleave", () => {
      if (!group.classList.contains("pinned")) hide(group);
    });
    img.addEventListener("click", (e) => {
      if (group.classList.toggle("pinned")) { at(e, group); render(group); }
    });
  }
  level.addEventListener("change", () => {
    for (const group of document.querySelectorAll(".group")) {
      if (group.querySelector("canvas.zoom:not([hidden])")) render(group);
    }
  });
  window.addEventListener("load", () => {
    const imgs = Array.from(document.images);
    Promise.all(imgs.map((i) => i.decode().then(() => i.naturalWidth > 0, () => false))).then((ok) => {
      const bad = ok.filter((x) => !x).length;
      if (bad) console.error(bad + " of " + imgs.length + " images failed to decode");
      document.body.dataset.ready = bad ? "failed " + bad + "/" + imgs.length : "ok " + imgs.length;
    });
  });
})();
