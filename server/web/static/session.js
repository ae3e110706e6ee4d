// The idle logout of a logged-in page (server/web/session.py): the server ends a session
// idle_logout_s after its user's last action; this script reports the user's clicks, keys and
// scrolling (never the page's own refreshes) and leaves for the login page when the session
// has ended, for want of use or because an engineer disabled or reset the user; a page whose
// user's role changed is drawn again.
"use strict";

(function () {
  if (!document.getElementById("logout")) return;  // not logged in: the login page, a kiosk
  const CHECK_MS = 5000;  // how often the page asks whether its session still lives
  let idleS = null;       // the station file's page.idle_logout_s, from the server
  let deadline = null;    // Date.now() when the server ends the session, as last told
  let sentAt = 0, pending = false, leaving = false;

  function leave(idle) {
    if (leaving) return;
    leaving = true;
    const next = encodeURIComponent(window.location.pathname + window.location.search);
    fetch("/web/logout", {method: "POST", credentials: "same-origin",
      headers: {"Accept": "application/json"}}).catch(() => {})
      .finally(() => window.location.assign("/login?next=" + next + (idle ? "&idle=1" : "")));
  }

  function take(r) {
    if (r.status === 401) { leave(deadline !== null && Date.now() >= deadline); return null; }
    if (!r.ok) return null;
    return r.json().then((d) => {
      // A role changed by an engineer applies at once: the page is drawn again for the new one.
      const shown = document.querySelector("header .who b[data-role]");
      if (shown && d.role !== shown.dataset.role) { window.location.reload(); return; }
      idleS = d.idle_logout_s;
      deadline = Date.now() + d.idle_left_s * 1000;
      document.body.dataset.idleLogoutS = String(idleS);
    });
  }

  function ask(method, url) {
    return fetch(url, {method: method, credentials: "same-origin",
      headers: {"Accept": "application/json"}}).then(take).catch(() => {});
  }

  // Every action restarts the server's idle time; at most one report per gap (a tenth of the
  // idle time, at most 10 s), and the last action of a burst is reported after it.
  function gapMs() { return Math.min((idleS || 10) * 100, 10000); }
  function report() {
    pending = false;
    sentAt = Date.now();
    ask("POST", "/web/session/activity");
  }
  function acted() {
    if (leaving) return;
    const wait = sentAt + gapMs() - Date.now();
    if (wait <= 0) report();
    else if (!pending) { pending = true; setTimeout(report, wait); }
  }
  ["pointerdown", "keydown", "wheel", "touchstart"].forEach((name) =>
    window.addEventListener(name, acted, {capture: true, passive: true}));

  setInterval(() => {
    if (!leaving && deadline !== null && Date.now() >= deadline) ask("GET", "/web/session");
  }, 250);
  setInterval(() => { if (!leaving) ask("GET", "/web/session"); }, CHECK_MS);
  ask("GET", "/web/session");
})();
