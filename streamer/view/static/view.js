// pvt view: polls /api/state every 100 ms and draws the cell (streamer/view/server.py says what it serves).
// window.pvtView holds what is plotted (the tests read it through the DevTools protocol).
(function () {
  "use strict";
  var WINDOW_S = 10;  // seconds of history on the plots
  var LABELS = {stop: "STOP", estop: "EMERGENCY STOP", hold: "HOLD", resume: "RESUME"};
  var view = window.pvtView = {after: -1, polls: 0, axes: {}, charts: {}, role: null, verbs: null, last: null};

  function el(tag, attrs, text) {
    var e = document.createElement(tag);
    Object.keys(attrs || {}).forEach(function (k) { e.setAttribute(k, attrs[k]); });
    if (text !== undefined) { e.textContent = text; }
    return e;
  }

  function verbButtons(verbs) {
    var box = document.getElementById("verbs");
    box.textContent = "";
    verbs.forEach(function (v) {
      var b = el("button", {id: "btn-" + v, type: "button"}, LABELS[v] || v);
      b.addEventListener("click", function () { post(v); });
      box.appendChild(b);
    });
  }

  function post(verb) {
    var msg = document.getElementById("message");
    msg.textContent = verb + "…";
    fetch("/api/" + verb, {method: "POST", headers: {"X-Pvt-View": "1"}})
      .then(function (r) { return r.json().then(function (j) { return [r.status, j]; }); })
      .then(function (a) {
        msg.textContent = a[0] === 200 ? verb + ": " + (a[1].message || "done") : verb + " refused: " + (a[1].message || a[1].error);
      })
      .catch(function (e) { msg.textContent = verb + " failed: " + e; });
  }

  function axisCard(name, unit) {
    var card = el("div", {"class": "axis", id: "axis-" + name});
    var h = el("h3");
    h.appendChild(el("span", {}, name + (unit ? " [" + unit + "]" : "")));
    h.appendChild(el("span", {"class": "state", id: "state-" + name}, ""));
    card.appendChild(h);
    var pos = el("div", {id: "plot-" + name});
    var fe = el("div", {id: "fe-" + name});
    card.appendChild(pos);
    card.appendChild(fe);
    var fifo = el("div", {"class": "fifo", id: "fifo-" + name});
    fifo.appendChild(el("div", {"class": "fill"}));
    fifo.appendChild(el("div", {"class": "mark under"}));
    fifo.appendChild(el("div", {"class": "mark over"}));
    card.appendChild(fifo);
    card.appendChild(el("div", {"class": "fifo-text", id: "fifo-text-" + name}, "FIFO -"));
    document.getElementById("axes").appendChild(card);
    var width = Math.max(360, card.clientWidth - 16);
    var axes = view.axes[name] = {t: [], position: [], demand: [], error: []};
    view.charts[name] = {
      position: new uPlot({width: width, height: 160, legend: {show: true}, scales: {x: {time: false}},
        series: [{label: "t [s]"}, {label: "position", stroke: "#1f77b4", width: 2},
                 {label: "demand (plan)", stroke: "#ff7f0e", width: 1, dash: [6, 3]}]},
        [axes.t, axes.position, axes.demand], pos),
      error: new uPlot({width: width, height: 90, legend: {show: true}, scales: {x: {time: false}},
        series: [{label: "t [s]"}, {label: "following error", stroke: "#d62728", width: 1}]},
        [axes.t, axes.error], fe)
    };
  }

  function addSample(m) {
    (m.axes || []).forEach(function (a) {
      var ax = view.axes[a.name];
      if (!ax || a.position === null || a.position === undefined) { return; }
      ax.t.push(m.t);
      ax.position.push(a.position);
      ax.demand.push(a.position_demand === null ? a.position : a.position_demand);
      ax.error.push(a.position_demand === null ? 0 : a.position - a.position_demand);
      while (ax.t.length && m.t - ax.t[0] > WINDOW_S) {
        ax.t.shift(); ax.position.shift(); ax.demand.shift(); ax.error.shift();
      }
    });
  }

  function drawAxes(m, marks) {
    (m.axes || []).forEach(function (a) {
      var ax = view.axes[a.name];
      if (!ax) { return; }
      var t0 = ax.t.length ? ax.t[ax.t.length - 1] : 0;
      var rel = ax.t.map(function (t) { return t - t0; });
      var ch = view.charts[a.name];
      ch.position.setData([rel, ax.position, ax.demand]);
      ch.error.setData([rel, ax.error]);
      document.getElementById("state-" + a.name).textContent = a.state + " · " + a.positioning;
      var box = document.getElementById("fifo-" + a.name);
      var size = marks.fifo_size;
      box.querySelector(".fill").style.width = (a.fifo_fill === null ? 0 : 100 * a.fifo_fill / size) + "%";
      box.querySelector(".under").style.left = (100 * marks.underflow / size) + "%";
      box.querySelector(".over").style.left = (100 * marks.overflow / size) + "%";
      document.getElementById("fifo-text-" + a.name).textContent = "FIFO " + (a.fifo_fill === null ? "-" : a.fifo_fill) +
        "/" + size + " (watermarks " + marks.underflow + ", " + marks.overflow + ")";
    });
  }

  function drawStatus(s, m) {
    var ready = document.getElementById("ready");
    var held = s.held || (m && m.held);
    var ok = m ? m.ready : s.ready;
    ready.textContent = !ok ? "NOT READY" + (m && m.reason ? ": " + m.reason : "") : (held ? "ready, queue HELD" : "ready");
    ready.className = "badge" + (!ok ? " bad" : (held ? " held" : ""));
    var job = m && m.job_id ? "job " + m.job_id + " " + (m.job_state || "") : "no job";
    document.getElementById("job").textContent = job;
    var p = m && typeof m.progress === "number" ? m.progress : 0;
    document.getElementById("progress").style.width = (100 * p) + "%";
    var q = document.getElementById("queue");
    q.textContent = "";
    (s.queue || []).forEach(function (j) { q.appendChild(el("li", {}, j.job_id + " (" + j.kind + ")")); });
    if (!(s.queue || []).length) { q.appendChild(el("li", {"class": "empty"}, "empty")); }
  }

  function drawEvents(events) {
    var list = document.getElementById("events");
    list.textContent = "";
    // a job's progress events (running, cancelling, halting: many a second) are summed up by the newest of each
    var newest = {};
    events.forEach(function (e, i) { newest[e.job_id + " " + e.type] = i; });
    events = events.filter(function (e, i) {
      return ["running", "cancelling", "halting"].indexOf(e.type) < 0 || newest[e.job_id + " " + e.type] === i;
    });
    events.slice(-15).reverse().forEach(function (e) {
      var err = e.error && e.error.code ? " " + e.error.code : "";
      var p = typeof e.progress === "number" ? " " + (100 * e.progress).toFixed(0) + "%" : "";
      list.appendChild(el("li", {}, new Date(1000 * e.t).toLocaleTimeString() + " " + e.job_id + " " + e.type + p + err));
    });
  }

  function poll() {
    fetch("/api/state?after=" + view.after).then(function (r) { return r.json(); }).then(function (st) {
      view.polls += 1;
      if (view.role === null) {
        view.role = st.role;
        view.verbs = st.verbs;
        document.getElementById("cell").textContent = "cell " + st.cell + " (" + st.role + ")";
        verbButtons(st.verbs);
      }
      var units = (st.status && st.status.units) || {};
      st.telemetry.forEach(function (m) {
        (m.axes || []).forEach(function (a) { if (!view.axes[a.name]) { axisCard(a.name, units[a.name]); } });
        addSample(m);
        view.after = Math.max(view.after, m.seq);
        view.last = m;
      });
      if (view.last) { drawAxes(view.last, st.watermarks); }
      drawStatus(st.status || {}, view.last);
      drawEvents(st.events || []);
      view.status = st.status;
    }).catch(function () {}).then(function () { setTimeout(poll, 100); });
  }
  poll();
})();
