// The scene viewer (viewer.py): switch the drawn layers and annotators on and off, and zoom
// the image with the buttons or Ctrl + wheel (a touchpad's pinch), around the pointer.
// Without this script the page shows every layer at the size that fits.
"use strict";
const MAX_ZOOM = 8;

for (const figure of document.querySelectorAll("figure.viewer")) {
  const form = figure.querySelector("form.layers");
  const controls = figure.querySelector(".zoom");
  const frame = figure.querySelector(".frame");
  const stage = figure.querySelector(".stage");
  const image = stage.querySelector("img");
  let scale = 1, fitWidth = 0;  // the image's width on the page at fit size, letterbox aside

  if (form) {
    form.hidden = false;
    form.addEventListener("change", () => {
      const on = (name) => new Set(Array.from(form.querySelectorAll(`input[name=${name}]:checked`),
                                              (input) => input.value));
      const layers = on("layer"), annotators = on("annotator");
      for (const shape of figure.querySelectorAll(".shape")) {
        const annotator = shape.dataset.annotator;
        shape.classList.toggle("off", !layers.has(shape.dataset.layer)
                                      || (annotator !== "" && !annotators.has(annotator)));
      }
    });
  }

  // Zoom to `next` (1: fit), keeping the image point under (x, y) of the frame in place.
  const zoomTo = (next, x = frame.clientWidth / 2, y = frame.clientHeight / 2) => {
    if (scale === 1) {
      fitWidth = Math.min(image.clientWidth,
                          image.clientHeight * image.naturalWidth / image.naturalHeight);
    }
    const pointX = (frame.scrollLeft + x) / scale, pointY = (frame.scrollTop + y) / scale;
    scale = Math.min(MAX_ZOOM, Math.max(1, next));
    figure.classList.toggle("zoomed", scale > 1);
    stage.style.width = scale > 1 ? `${fitWidth * scale}px` : "";
    frame.scrollLeft = pointX * scale - x;
    frame.scrollTop = pointY * scale - y;
  };

  controls.hidden = false;
  controls.addEventListener("click", (event) => {
    const button = event.target.closest("button[data-zoom]");
    if (button) zoomTo(Number(button.dataset.zoom) ? scale * Number(button.dataset.zoom) : 1);
  });
  frame.addEventListener("wheel", (event) => {
    if (!event.ctrlKey) return;  // a plain wheel scrolls the page, or pans the zoomed image
    event.preventDefault();
    const box = frame.getBoundingClientRect();
    zoomTo(scale * Math.exp(-event.deltaY / 300), event.clientX - box.left, event.clientY - box.top);
  }, {passive: false});
}
