// Brushing the scene log's histogram (webui/histogram.py): a pointer dragged across its bars
// sets the log's time range to the bars it went over, from the first bar's start to the last
// bar's end, with the other filters as they are, and loads it. Each bar stays a link (a
// click, Enter): the range of one bar, from the keyboard and without this script.
const figure = document.querySelector("figure.histogram");
const svg = figure?.querySelector("svg");
const bars = figure ? [...figure.querySelectorAll("a.bar")] : [];
let first = null, last = null, dragged = false;

function barAt(event) {
  const box = svg.getBoundingClientRect();
  const i = Math.floor((event.clientX - box.left) / box.width * bars.length);
  return Math.min(Math.max(i, 0), bars.length - 1);
}

function mark() {
  const [low, high] = [Math.min(first, last), Math.max(first, last)];
  bars.forEach((bar, i) => bar.classList.toggle("brushed", dragged && i >= low && i <= high));
}

function range() {
  const [low, high] = [Math.min(first, last), Math.max(first, last)];
  const link = (bar) => new URL(bar.getAttribute("href"), location.href);  // (an SVG link)
  const url = link(bars[low]);
  url.searchParams.set("until", link(bars[high]).searchParams.get("until"));
  url.searchParams.delete("before");
  return url;
}

if (svg && bars.length) {
  svg.addEventListener("dragstart", (event) => event.preventDefault());  // not the link
  svg.addEventListener("pointerdown", (event) => {
    if (event.button !== 0) return;
    first = last = barAt(event);
    dragged = false;
  });
  svg.addEventListener("pointermove", (event) => {
    if (first === null) return;
    last = barAt(event);
    if (!dragged && last !== first) {
      dragged = true;
      svg.setPointerCapture(event.pointerId);  // beyond the bars too (a click keeps its link)
    }
    mark();
  });
  svg.addEventListener("pointerup", () => {
    if (first === null) return;
    if (dragged) location.assign(range());
    first = dragged ? first : null;  // a click on one bar is its link's
  });
  svg.addEventListener("click", (event) => {
    if (dragged) event.preventDefault();  // the drag loads its range, not the bar clicked
  }, true);
}
