/* cobgs report: sortable tables and the method comparison slider.
   Plain JavaScript, no library and no network: the page must work from file://. */
(function () {
  "use strict";

  // -- sortable tables ------------------------------------------------------------------
  // Cells carry their raw value in data-sort; numeric columns (th.num) compare as numbers.
  // Empty values always go last, whichever the direction, so "not measured" never wins.
  function cellValue(row, index, numeric) {
    var cell = row.cells[index];
    var raw = cell ? cell.getAttribute("data-sort") : "";
    if (raw === null || raw === "") return null;
    if (numeric) {
      var n = parseFloat(raw);
      return isNaN(n) ? null : n;
    }
    return raw.toLowerCase();
  }

  function sortTable(table, th) {
    var headers = Array.prototype.slice.call(th.parentNode.children);
    var index = headers.indexOf(th);
    var numeric = th.classList.contains("num");
    var ascending = th.getAttribute("aria-sort") !== "ascending";
    headers.forEach(function (h) { if (h.hasAttribute("aria-sort")) h.setAttribute("aria-sort", "none"); });
    th.setAttribute("aria-sort", ascending ? "ascending" : "descending");
    var body = table.tBodies[0];
    var rows = Array.prototype.slice.call(body.rows);
    var keyed = rows.map(function (row, i) { return { row: row, v: cellValue(row, index, numeric), i: i }; });
    keyed.sort(function (a, b) {
      if (a.v === null && b.v === null) return a.i - b.i;
      if (a.v === null) return 1;
      if (b.v === null) return -1;
      var c = a.v < b.v ? -1 : a.v > b.v ? 1 : 0;
      if (c === 0) return a.i - b.i; // stable
      return ascending ? c : -c;
    });
    keyed.forEach(function (k) { body.appendChild(k.row); });
  }

  function initTables() {
    var tables = document.querySelectorAll("table.sortable");
    Array.prototype.forEach.call(tables, function (table) {
      var ths = table.tHead ? table.tHead.rows[0].cells : [];
      Array.prototype.forEach.call(ths, function (th) {
        var button = th.querySelector("button.sort");
        if (button) button.addEventListener("click", function () { sortTable(table, th); });
      });
    });
  }

  // -- comparison slider ------------------------------------------------------------------
  // Left: the reference method; right: the peer chosen with the buttons, clipped by the
  // slider. The kind buttons switch both sides to another picture (errors, crop, ...).
  function initCompare(box) {
    var dataNode = box.querySelector("script.cmp-data");
    if (!dataNode) return;
    var data = JSON.parse(dataNode.textContent).methods;
    var ref = box.getAttribute("data-ref");
    var left = box.querySelector("img.cmp-left");
    var right = box.querySelector("img.cmp-right");
    var tagRight = box.querySelector(".cmp-tag.right");
    var handle = box.querySelector(".cmp-handle");
    var range = box.querySelector("input.cmp-range");
    var kindButtons = box.querySelectorAll("button[data-kind]");
    var methodButtons = box.querySelectorAll("button[data-method]");
    var state = { kind: null, method: null };

    function pressed(buttons, attr) {
      for (var i = 0; i < buttons.length; i++) {
        if (buttons[i].getAttribute("aria-pressed") === "true") return buttons[i].getAttribute(attr);
      }
      return buttons.length ? buttons[0].getAttribute(attr) : null;
    }

    function show(img, method) {
      var url = (data[method] || {})[state.kind];
      // A method without this picture keeps its last image hidden: never an empty src,
      // which a browser would report as a broken image.
      if (url) {
        if (img.getAttribute("src") !== url) img.setAttribute("src", url);
        img.classList.remove("unavailable");
        img.alt = method + ": " + state.kind;
      } else {
        img.classList.add("unavailable");
      }
    }

    function render() {
      show(left, ref);
      show(right, state.method);
      tagRight.textContent = state.method;
      Array.prototype.forEach.call(kindButtons, function (b) {
        b.setAttribute("aria-pressed", b.getAttribute("data-kind") === state.kind ? "true" : "false");
      });
      Array.prototype.forEach.call(methodButtons, function (b) {
        b.setAttribute("aria-pressed", b.getAttribute("data-method") === state.method ? "true" : "false");
      });
    }

    function slide() {
      var v = Number(range.value);
      right.style.clipPath = "inset(0 0 0 " + v + "%)";
      handle.style.left = v + "%";
    }

    state.kind = pressed(kindButtons, "data-kind");
    state.method = pressed(methodButtons, "data-method");
    Array.prototype.forEach.call(kindButtons, function (b) {
      b.addEventListener("click", function () { state.kind = b.getAttribute("data-kind"); render(); });
    });
    Array.prototype.forEach.call(methodButtons, function (b) {
      b.addEventListener("click", function () { state.method = b.getAttribute("data-method"); render(); });
    });
    range.addEventListener("input", slide);
    render();
    slide();
  }

  function init() {
    initTables();
    Array.prototype.forEach.call(document.querySelectorAll(".compare"), initCompare);
    document.documentElement.setAttribute("data-report-ready", "1");
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();
