// The playback page (webui/playback.py) without reloads: steps, marks on the timeline, the
// time slider and the follow form fetch the page they lead to and put its content in place
// of this one's; Play follows the "next" step every PERIOD ms until the last scene; the arrow
// keys step. The page's content arrives rendered and escaped by the server: parsed, never run.
const PERIOD = 1000;
const main = document.querySelector("main");
const play = document.createElement("button");
play.type = "button";
play.className = "play";
let playing = false, run = 0;  // run: which press of Play the loop belongs to

async function load(url) {
  const answer = await fetch(url);
  const page = new DOMParser().parseFromString(await answer.text(), "text/html");
  main.replaceChildren(...page.querySelector("main").childNodes);
  history.replaceState(null, "", answer.url);
  document.title = page.title;
  attach();
}

function attach() {
  play.textContent = playing ? "Pause" : "Play";
  main.querySelector("nav.steps")?.prepend(play);
}

function wait(ms) {
  return new Promise((done) => setTimeout(done, ms));
}

play.addEventListener("click", async () => {
  playing = !playing;
  attach();
  const mine = ++run;
  while (playing && run === mine) {
    await wait(PERIOD);
    if (!playing || run !== mine) break;
    const next = main.querySelector("nav.steps a[rel=next]");
    if (!next) { playing = false; attach(); break; }
    await load(next.getAttribute("href"));
  }
});

main.addEventListener("click", (event) => {  // a step, or a mark on the timeline
  const link = event.target.closest("nav.steps a, .marks a");
  if (!link || event.ctrlKey || event.metaKey || event.shiftKey) return;
  event.preventDefault();
  load(link.getAttribute("href"));  // (an SVG link's href is no string)
});

main.addEventListener("submit", (event) => {
  const form = event.target.closest("form[action='/playback']");
  if (!form) return;
  event.preventDefault();
  load(`/playback?${new URLSearchParams(new FormData(form))}`);
});

main.addEventListener("change", (event) => {  // the slider let go, another robot or map chosen
  const form = event.target.form;
  if (!form?.matches("form.timeline")) return;
  if (event.target.name === "robot") form.elements.map.value = "";  // its maps are others
  form.requestSubmit();
});

let steps = Promise.resolve();  // the arrow keys' steps, each from where the one before led

document.addEventListener("keydown", (event) => {  // left and right arrows step, as in players
  const rel = { ArrowLeft: "prev", ArrowRight: "next" }[event.key];
  if (!rel || event.target.closest("input, select, textarea")) return;
  event.preventDefault();
  steps = steps.then(() => {
    const link = main.querySelector(`nav.steps a[rel=${rel}]`);
    return link && load(link.getAttribute("href"));
  }).catch(() => {});
});

attach();
