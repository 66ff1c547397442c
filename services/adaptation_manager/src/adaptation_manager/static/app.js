// The adaptation manager's dashboard. Everything it shows comes from the fabric
// (component names, log lines, reasons): it is set as text (textContent, text nodes),
// never parsed as HTML.
"use strict";

const MAX_LOG = 200;
const MAX_CYCLES = 30;
const MAX_PLAN_CYCLES = 15;
const MAX_PLANS = 100;
const STAGES = ["monitor", "analyse", "plan", "legitimate", "execute"];

const state = { components: new Map(), cycles: new Map(), plans: new Map(), trust: new Map() };
let ws = null;
let nextId = 1;
let retry = 500;

function el(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k === "class") node.className = v;
    else if (k.startsWith("data-")) node.setAttribute(k, String(v));
    else if (k === "title") node.title = String(v);
    else if (k === "hidden") node.hidden = Boolean(v);
  }
  for (const c of children) {
    if (c === null || c === undefined) continue;
    node.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return node;
}

function badge(text) {
  const cls = String(text).replace(/[^a-z]/gi, "");
  return el("span", { class: "badge " + cls, "data-field": "state" }, text);
}

function time(ns) {
  if (!ns) return "-";
  const d = new Date(Number(ns) / 1e6);
  return d.toISOString().slice(11, 23);
}

function ms(ns) {
  return (Number(ns) / 1e6).toFixed(1) + " ms";
}

// -- components, grouped by compute node ----------------------------------------------------

function nodeBox(name) {
  const key = name || "(compute node not known yet)";
  let box = document.querySelector(`section.node[data-node="${CSS.escape(key)}"]`);
  if (box) return box.querySelector("tbody");
  const body = el("tbody");
  box = el("section", { class: "node", "data-node": key },
    el("h3", {}, "compute node ", el("span", { "data-field": "node-name" }, key)),
    el("table", {},
      el("thead", {}, el("tr", {}, ...["component", "stage", "state", "last cycle", "p50 / p99",
        "inbox", "dropped", "rejected", "restarts", ""].map((h) => el("th", {}, h)))),
      body));
  const all = [...document.querySelectorAll("#nodes section.node")];
  const after = all.find((b) => b.dataset.node > key);
  document.getElementById("nodes").insertBefore(box, after || null);
  return body;
}

function componentRow(c) {
  let row = document.querySelector(`tr[data-component="${CSS.escape(c.name)}"]`);
  if (!row) {
    row = el("tr", { "data-component": c.name });
    for (const f of ["name", "stage", "state", "last_cycle", "latency", "inbox", "dropped",
      "rejected", "restarts"]) {
      row.append(el("td", { "data-cell": f }));
    }
    const actions = el("td", { "data-cell": "actions" });
    for (const verb of ["pause", "resume", "restart"]) {
      const b = el("button", { "data-verb": verb }, verb);
      b.addEventListener("click", () => command(row.dataset.component, verb, b));
      actions.append(b);
    }
    row.append(actions);
  }
  return row;
}

function renderComponent(c) {
  state.components.set(c.name, c);
  const row = componentRow(c);
  const node = c.compute_node || "(compute node not known yet)";
  row.dataset.node = node;
  row.dataset.state = c.state;
  const body = nodeBox(c.compute_node);
  if (row.parentElement !== body) {
    const old = row.parentElement;
    const next = [...body.children].find((r) => r.dataset.component > c.name);
    body.insertBefore(row, next || null);
    if (old && !old.children.length) old.closest("section.node").remove();
  }
  const cell = (f) => row.querySelector(`td[data-cell="${f}"]`);
  cell("name").textContent = c.name;
  cell("stage").textContent = c.stage || "-";
  cell("state").replaceChildren(badge(c.state));
  cell("state").title = c.paused_policy || "";
  cell("last_cycle").textContent = c.last_cycle ? c.last_cycle.slice(0, 12) : "-";
  cell("latency").textContent = c.answers ? `${c.p50_ms.toFixed(2)} / ${c.p99_ms.toFixed(2)} ms` : "-";
  cell("inbox").textContent = c.inbox;
  cell("dropped").textContent = c.dropped;
  cell("rejected").textContent = c.rejected;
  cell("restarts").textContent = c.restarts;
  for (const b of row.querySelectorAll("button")) {
    b.disabled = !c.alive || !c.answers;
  }
}

function command(component, verb, button) {
  const out = document.getElementById("command-result");
  if (!ws || ws.readyState !== WebSocket.OPEN) {
    out.textContent = "not connected to the manager";
    return;
  }
  const id = nextId++;
  button.disabled = true;
  out.textContent = `${verb} ${component}...`;
  ws.send(JSON.stringify({ t: "command", id, component, verb }));
}

function onResult(r) {
  const out = document.getElementById("command-result");
  out.textContent = `${r.verb} ${r.component}: ${r.ok ? "ok" : "refused"} - ${r.message}`;
  out.dataset.ok = r.ok ? "true" : "false";
  const c = state.components.get(r.component);
  if (c) renderComponent(c);
}

// -- cycles ---------------------------------------------------------------------------------

function renderCycle(v) {
  state.cycles.set(v.cycle, v);
  const body = document.querySelector("#cycles tbody");
  let row = body.querySelector(`tr[data-cycle="${CSS.escape(v.cycle)}"]`);
  const fresh = !row;
  if (fresh) {
    row = el("tr", { class: "cycle", "data-cycle": v.cycle });
    row.addEventListener("click", () => showChain(row.dataset.cycle));
  }
  const span = Math.max(1, v.end - v.start);
  const bar = el("div", { class: "bar" });
  for (const call of v.calls) {
    const left = Math.max(0, ((call.start - v.start) / span) * 100);
    const width = Math.max(0.5, (call.duration_ns / span) * 100);
    const s = el("span", {
      class: STAGES.includes(call.stage) ? call.stage : "other",
      title: `${call.node}.${call.handler} on ${call.trigger_key}: ${ms(call.duration_ns)}` +
        (call.ok ? "" : ` FAILED: ${call.error}`),
    });
    s.style.left = left.toFixed(2) + "%";
    s.style.width = width.toFixed(2) + "%";
    bar.append(s);
  }
  row.replaceChildren(
    el("td", { class: "mono" }, v.cycle.slice(0, 12)),
    el("td", {}, badge(v.state)),
    el("td", {}, v.stages.join(" > ") || "-"),
    el("td", {}, bar),
    el("td", {}, v.end ? ms(v.end - v.start) : "-"),
    el("td", {}, v.outstanding.join("; ")),
  );
  row.dataset.state = v.state;
  row.dataset.plan = v.stages.includes("plan") ? "yes" : "no";
  row.hidden = plansOnly() && row.dataset.plan !== "yes";
  if (fresh) {
    body.prepend(row);
    trimCycles(body);
  }
}

function plansOnly() {
  return document.getElementById("plans-only").checked;
}

// the oldest rows go first; cycles that reached the plan stage are kept longer (most
// cycles only monitor and analyse)
function trimCycles(body) {
  const rows = [...body.children];
  const planned = rows.filter((r) => r.dataset.plan === "yes");
  const others = rows.filter((r) => r.dataset.plan !== "yes");
  const drop = [...planned.slice(MAX_PLAN_CYCLES), ...others.slice(MAX_CYCLES)];
  for (const r of drop) {
    state.cycles.delete(r.dataset.cycle);
    r.remove();
  }
}

async function showChain(cycle) {
  const pre = document.getElementById("chain");
  pre.hidden = false;
  pre.textContent = "asking the manager...";
  try {
    const res = await fetch("/api/trace?cycle=" + encodeURIComponent(cycle));
    const reply = await res.json();
    if (!reply.ok) { pre.textContent = reply.message; return; }
    const t = reply.trace;
    const lines = [`cycle ${t.cycle} (${t.state}) ${t.root_key}: ${t.total_ms.toFixed(1)} ms`];
    for (const s of t.steps) {
      const pad = "  ".repeat(s.depth + 1);
      const wait = s.wait_ms === null ? "" : `, waited ${s.wait_ms.toFixed(1)} ms`;
      lines.push(`${pad}+${s.offset_ms.toFixed(1)} ms ${s.stage || "-"} ${s.node}.${s.handler} ` +
        `on ${s.trigger_key} (${s.duration_ms.toFixed(1)} ms${wait})${s.ok ? "" : " FAILED: " + s.error}`);
      for (const k of s.sent) lines.push(`${pad}    -> ${k}`);
    }
    for (const o of t.outstanding) lines.push("  outstanding: " + o);
    pre.textContent = lines.join("\n");
  } catch (e) {
    pre.textContent = "could not ask the manager: " + e;
  }
}

// -- plans, trust, watches, log ------------------------------------------------------------

function renderPlan(p) {
  state.plans.set(p.plan, p);
  const body = document.querySelector("#plans tbody");
  let row = body.querySelector(`tr[data-plan="${CSS.escape(p.plan)}"]`);
  const fresh = !row;
  if (fresh) row = el("tr", { "data-plan": p.plan });
  row.replaceChildren(
    el("td", { class: "mono", title: "cycle " + p.cycle }, p.plan.slice(0, 12)),
    el("td", {}, badge(p.status)),
    el("td", {}, p.proposer || "-"),
    el("td", {}, p.legitimator || "-"),
    el("td", {}, p.executor || "-"),
    el("td", {}, p.reason || ""),
  );
  if (fresh) {
    body.prepend(row);
    while (body.children.length > MAX_PLANS) body.lastElementChild.remove();
  }
}

function renderTrust(t) {
  state.trust.set(t.stream, t);
  const body = document.querySelector("#trust tbody");
  let row = body.querySelector(`tr[data-stream="${CSS.escape(t.stream)}"]`);
  if (!row) {
    row = el("tr", { "data-stream": t.stream });
    body.append(row);
  }
  row.replaceChildren(
    el("td", {}, t.stream),
    el("td", {}, t.false ? badge("false") : (t.deferred ? "⊥" : t.value)),
    el("td", {}, t.tick),
  );
}

function prependItem(listId, item, max) {
  const list = document.getElementById(listId);
  list.prepend(item);
  while (list.children.length > max) list.lastElementChild.remove();
}

function renderVerdict(v) {
  const head = v.kind === "trigger"
    ? `${time(v.ts)} trigger ${v.stream} fired (${v.severity || "info"}): ${v.message || v.expr}`
    : `${time(v.ts)} ${v.stream} = ${v.value} at tick ${v.tick}: ${v.expr}`;
  const item = el("li", { class: v.severity || "warning" }, head);
  for (const c of v.because) {
    const input = c.input ? ` (input ${c.input}, tick ${c.input_tick === null ? "-" : c.input_tick})` : "";
    const line = el("div", { class: "cause" }, `${"  ".repeat(c.depth)}because ${c.expr} = ${c.value}${input}`);
    item.append(line);
  }
  if (v.truncated) item.append(el("div", { class: "cause" }, "(more causes not shown)"));
  prependItem("verdicts", item, MAX_LOG);
}

function renderAlert(a) {
  prependItem("alerts", el("li", { class: "warning", "data-kind": a.kind },
    `${time(a.ts)} [${a.kind}] ${a.message}`), MAX_LOG);
}

function renderLog(l) {
  prependItem("log", el("li", { class: l.level, "data-kind": l.kind },
    `${time(l.ts)} ${l.level} ${l.source}: ${l.text}`), MAX_LOG);
}

function renderCounters(c) {
  const parts = [
    ["cycles", c["cycles"] || 0],
    ["stalled", c["cycles.stalled"] || 0],
    ["proposed", c["plans.proposed"] || 0],
    ["approved", c["plans.approved"] || 0],
    ["rejected", c["plans.rejected"] || 0],
    ["executed", c["plans.executed"] || 0],
    ["gone", c["alerts.gone"] || 0],
    ["failed", c["alerts.failed"] || 0],
    ["trust false", c["alerts.trust"] || 0],
  ];
  document.getElementById("counters").replaceChildren(
    ...parts.map(([k, v]) => el("span", { "data-counter": k }, `${k}: ${v}`)));
}

// -- the WebSocket ----------------------------------------------------------------------------

const RENDER = {
  component: renderComponent,
  cycle: renderCycle,
  plan: renderPlan,
  trust: renderTrust,
  verdict: renderVerdict,
  alert: renderAlert,
  log: renderLog,
};

function onSnapshot(s) {
  document.getElementById("system").textContent = s.system;
  document.title = `RAP ${s.system}: adaptation manager`;
  document.getElementById("nodes").replaceChildren();
  for (const id of ["cycles", "plans", "trust"]) document.querySelector(`#${id} tbody`).replaceChildren();
  for (const id of ["verdicts", "alerts", "log"]) document.getElementById(id).replaceChildren();
  state.components.clear(); state.cycles.clear(); state.plans.clear(); state.trust.clear();
  s.components.forEach(renderComponent);
  s.cycles.forEach(renderCycle);
  s.plans.forEach(renderPlan);
  s.trust.forEach(renderTrust);
  s.verdicts.forEach(renderVerdict);
  s.alerts.forEach(renderAlert);
  s.log.forEach(renderLog);
  renderCounters(s.counters);
}

function setLink(text, cls) {
  const link = document.getElementById("link");
  link.textContent = text;
  link.className = "badge " + cls;
  link.dataset.state = cls;
}

function connect() {
  const url = (location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws";
  ws = new WebSocket(url);
  ws.onopen = () => { retry = 500; setLink("live", "connected"); };
  ws.onmessage = (ev) => {
    const msg = JSON.parse(ev.data);
    if (msg.t === "snapshot") onSnapshot(msg);
    else if (msg.t === "batch") {
      for (const item of msg.items) {
        const render = RENDER[item.k];
        if (render) render(item.v);
      }
      renderCounters(msg.counters);
    } else if (msg.t === "result") onResult(msg);
    else if (msg.t === "error") document.getElementById("command-result").textContent = msg.message;
  };
  ws.onclose = () => {
    setLink("reconnecting", "gone");
    setTimeout(connect, retry);
    retry = Math.min(retry * 2, 8000);
  };
}

document.getElementById("plans-only").addEventListener("change", () => {
  for (const row of document.querySelectorAll("#cycles tbody tr")) {
    row.hidden = plansOnly() && row.dataset.plan !== "yes";
  }
});
connect();
