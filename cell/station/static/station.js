// Cell station pages: the PIN keypad, the live page's server-sent events, confirmations. No libraries.
"use strict";

function keypad() {
  for (const pad of document.querySelectorAll(".keypad")) {
    const field = document.getElementById(pad.dataset.target);
    pad.addEventListener("click", (ev) => {
      const key = ev.target.closest("button")?.dataset.key;
      if (!key) return;
      if (key === "clear") field.value = "";
      else if (key === "back") field.value = field.value.slice(0, -1);
      else field.value += key;
      field.focus();
    });
  }
}

function confirmations() {
  // a form with data-question asks on the page itself (large buttons, no browser dialog)
  for (const form of document.querySelectorAll("form.confirm")) {
    form.addEventListener("submit", (ev) => {
      if (form.dataset.confirmed) return;
      ev.preventDefault();
      const box = document.createElement("div");
      box.className = "confirm-box";
      box.innerHTML = `<span></span><button type="button" class="stop" id="confirm-yes">Yes</button>` +
        `<button type="button" id="confirm-no">No</button>`;
      box.querySelector("span").textContent = form.dataset.question;
      form.querySelector("button").style.display = "none";
      form.appendChild(box);
      box.querySelector("#confirm-no").onclick = () => { box.remove(); form.querySelector("button").style.display = ""; };
      box.querySelector("#confirm-yes").onclick = () => {
        form.dataset.confirmed = "1";
        box.querySelector("span").textContent = "Stopping the run safely, then aborting it...";
        for (const b of box.querySelectorAll("button")) b.disabled = true;
        form.submit();
      };
    });
  }
  for (const form of document.querySelectorAll(".actions form:not(.confirm)")) {
    form.addEventListener("submit", () => { for (const b of form.querySelectorAll("button")) b.disabled = true; });
  }
}

function live() {
  const root = document.getElementById("live");
  if (!root) return;
  const set = (id, text) => { const el = document.getElementById(id); if (el) el.textContent = text; };
  const photo = document.getElementById("photo");
  photo.addEventListener("error", () => {  // its raw images removed meanwhile: the map alone
    photo.hidden = true;
    document.getElementById("pictures").classList.remove("with-photo");
  });
  const source = new EventSource(root.dataset.events);
  source.addEventListener("progress", (ev) => {
    const s = JSON.parse(ev.data);
    set("words", s.words);
    set("message", s.failed || s.message || "");
    set("view", s.view ?? "-");
    set("total", s.views_total || "-");
    set("done", s.views_done);
    set("elapsed", s.elapsed_text || "-");
    set("left", s.left_text || "-");
    set("leftnote", s.left_note || "");
    set("serial", s.serial || "-");
    set("part", s.part || "-");
    set("operator", s.user || "-");
    const share = s.state === "done" ? 1 : (s.views_total ? Math.min(s.views_done / s.views_total, 1) : 0);
    document.getElementById("bar").style.width = `${Math.round(100 * share)}%`;
    if (s.thumbnail) {
      const img = document.getElementById("thumb");
      if (img.getAttribute("src") !== s.thumbnail) img.src = s.thumbnail;
      set("thumbview", s.last_view + 1);
      // the photo while the view's raw images are kept; else the map alone, full size
      if (s.photo && photo.getAttribute("src") !== s.photo) photo.src = s.photo;
      photo.hidden = !s.photo;
      document.getElementById("pictures").classList.toggle("with-photo", Boolean(s.photo));
      set("photonote", s.photo ? ": the camera's picture, and (corner) what each pixel measured" : "");
    }
    for (const action of ["pause", "resume", "abort"]) {
      const button = document.getElementById(action);
      if (button && !button.closest("form").dataset.confirmed) button.disabled = !s.actions[action];
    }
    root.dataset.state = s.state || "starting";
    if (s.final) {
      source.close();
      if (!s.failed) window.location = root.dataset.verdict;
    }
  });
}

document.addEventListener("DOMContentLoaded", () => { keypad(); confirmations(); live(); });
