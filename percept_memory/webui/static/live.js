// The live page: each scene the server announces (/live/events) goes on top of the table.
// Rows arrive rendered and escaped by the server; they are parsed, never run.
"use strict";
const rows = document.querySelector("table.scenes tbody");
const status = document.getElementById("live-status");
const shown = Number(rows.dataset.shown);
const events = new EventSource("/live/events");

events.addEventListener("open", () => { status.textContent = "Live: new scenes appear on top."; });
events.addEventListener("error", () => { status.textContent = "Connection lost, reconnecting…"; });
events.addEventListener("scene", (event) => {
  const parsed = document.createElement("template");
  parsed.innerHTML = event.data;
  const row = parsed.content.querySelector("tr.scene");
  if (!row || rows.querySelector(`tr[data-scene="${row.dataset.scene}"]`)) return;
  row.classList.add("new");
  rows.prepend(row);
  while (rows.rows.length > shown) rows.deleteRow(-1);
  document.getElementById("no-scenes")?.remove();
});
