// crowdbench leaderboard site: click (or Enter on) a column header of a table.sortable to sort its rows.
// Numeric columns (th[data-type=num]) sort by each cell's data-sort value (the mean; empty = no value,
// always last); text columns by data-sort or the cell's text. A second click reverses the order.
"use strict";
(function () {
  function key(cell) {
    var v = cell.getAttribute("data-sort");
    return v === null ? cell.textContent.trim() : v;
  }

  function sortBy(table, col, th) {
    var body = table.tBodies[0];
    var dir = th.getAttribute("aria-sort") === "ascending" ? "descending" : "ascending";
    var sign = dir === "ascending" ? 1 : -1;
    var numeric = th.getAttribute("data-type") === "num";
    var rows = Array.prototype.slice.call(body.rows).map(function (row, i) {
      var k = key(row.cells[col]);
      return { row: row, i: i, k: numeric ? (k === "" ? NaN : parseFloat(k)) : k.toLowerCase() };
    });
    rows.sort(function (a, b) {
      var c;
      if (numeric) {
        var na = isNaN(a.k), nb = isNaN(b.k);
        if (na || nb) return na === nb ? a.i - b.i : (na ? 1 : -1); // no value: last either way
        c = a.k - b.k;
      } else {
        c = a.k < b.k ? -1 : a.k > b.k ? 1 : 0;
      }
      return c !== 0 ? sign * c : a.i - b.i;
    });
    rows.forEach(function (r) { body.appendChild(r.row); });
    Array.prototype.forEach.call(table.tHead.rows[0].cells, function (h) { h.removeAttribute("aria-sort"); });
    th.setAttribute("aria-sort", dir);
  }

  Array.prototype.forEach.call(document.querySelectorAll("table.sortable"), function (table) {
    if (!table.tHead || !table.tBodies.length) return;
    Array.prototype.forEach.call(table.tHead.rows[0].cells, function (th, col) {
      th.tabIndex = 0;
      th.addEventListener("click", function () { sortBy(table, col, th); });
      th.addEventListener("keydown", function (ev) {
        if (ev.key === "Enter" || ev.key === " ") { ev.preventDefault(); sortBy(table, col, th); }
      });
    });
  });
})();
