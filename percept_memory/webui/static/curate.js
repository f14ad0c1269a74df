// The correction forms (webui/curation.py). Each form.correct sends its fields as JSON to the
// API path in its data-api attribute, signed with the author's name (the page's #author field,
// remembered on this browser) and, once the server asks for it, the write token (#token, kept
// for the browser session). What the server answers is shown in the form's status line. After
// a correction the page reloads to show it, or, in a queue (data-then="next"), the next row's
// first field takes the focus: corrections go one after another from the keyboard.
const TOKEN = "pmem-token", AUTHOR = "pmem-author";
const author = document.getElementById("author");
const token = document.getElementById("token");
author.value ||= localStorage.getItem(AUTHOR) || "";
let refused = null;  // the form the server refused for want of a name or a token: Enter in
// either field sends it again
for (const field of [author, token]) {
  field.addEventListener("keydown", (event) => {
    if (event.key === "Enter" && refused) {
      event.preventDefault();
      refused.requestSubmit();
    }
  });
}

for (const form of document.querySelectorAll("form.correct")) {
  form.addEventListener("submit", send);
}
document.querySelector("form.correct[data-then=next] input")?.focus();  // a queue starts here

// A row whose correction is being saved takes no other until the answer came: a Tab and an
// Enter before it (the focus still in the row) sent a second correction of the same cluster.
const saving = new WeakSet();

async function send(event) {
  event.preventDefault();
  const form = event.currentTarget;
  const row = form.closest("tr, li") || form;
  if (saving.has(row)) return;
  const status = form.querySelector("[role=status]");
  const fields = new FormData(form);
  const body = Object.fromEntries(fields);
  const list = form.dataset.list;  // a field of many values (checkboxes): sent as a list
  if (list) body[list] = fields.getAll(list);
  body.author = author.value.trim();
  localStorage.setItem(AUTHOR, body.author);
  const headers = {"Content-Type": "application/json"};
  const secret = token.value || sessionStorage.getItem(TOKEN);
  if (secret) headers.Authorization = `Bearer ${secret}`;
  status.textContent = "Saving…";
  let answer;
  saving.add(row);
  try {
    answer = await fetch(form.dataset.api, {method: "POST", headers, body: JSON.stringify(body)});
  } finally {
    saving.delete(row);
  }
  if (answer.ok) {
    refused = null;
    if (secret) sessionStorage.setItem(TOKEN, secret);
    status.textContent = "Saved.";
    await done(form, (await answer.json()).map);
    return;
  }
  const {error} = await answer.json();
  status.textContent = error.problems.map((p) => p.message).join("; ") || error.message;
  refused = form;
  if (answer.status === 401 || answer.status === 403) {
    sessionStorage.removeItem(TOKEN);
    token.closest("[hidden]")?.removeAttribute("hidden");
    token.focus();
  } else if (error.problems.some((p) => p.path === "body.author")) {
    author.focus();
  }
}

async function done(form, map) {
  if (form.dataset.then !== "next") {
    await rebuilt(map, form.querySelector("[role=status]"));
    location.reload();
    return;
  }
  const row = form.closest("tr, li");
  if (!row?.classList.contains("corrected")) {  // the queue's count of clusters fixed
    const fixed = document.querySelector(".counts .fixed");
    if (fixed) fixed.textContent = Number(fixed.textContent) + 1;
  }
  row?.classList.add("corrected");
  row?.nextElementSibling?.querySelector("form.correct input, form.correct button")?.focus();
}

// A correction that changes who is who (merge, split, reject, undo) has its map's belief
// rebuilt by the memory pipeline: the map is marked, its scenes queued again and gone through.
// The page reloads once the map (the answer names it) has none left (at most REBUILD_WAIT_MS;
// after that the page itself says it is still being rebuilt), not before, when it would show
// the object as it was.
const REBUILD_WAIT_MS = 30000, REBUILD_POLL_MS = 300;
async function rebuilt(name, status) {
  const until = Date.now() + REBUILD_WAIT_MS;
  while (name && Date.now() < until) {
    const answer = await fetch("/api/pipeline");
    if (!answer.ok) return;
    const map = (await answer.json()).maps.find((row) => row.map === name);
    if (!map || !(map.rebuilding || map.pending)) return;
    status.textContent = "Saved. The belief is being rebuilt with it…";
    await new Promise((resolve) => setTimeout(resolve, REBUILD_POLL_MS));
  }
}
