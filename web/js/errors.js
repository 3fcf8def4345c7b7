// Collects script errors, unhandled rejections and console.error calls in
// window.__fleetslamErrors, before any module runs, so that the browser test can assert that
// the page produced none. Loaded as a classic script (no module) from index.html.
(function () {
  "use strict";
  var errors = [];
  window.__fleetslamErrors = errors;
  function text(v) {
    if (v instanceof Error) return v.stack || String(v);
    try { return typeof v === "string" ? v : JSON.stringify(v); } catch (_) { return String(v); }
  }
  window.addEventListener("error", function (e) {
    // Script errors carry a message; failed resource loads (img, script, link) a target.
    var where = e.filename ? " (" + e.filename + ":" + e.lineno + ")" : "";
    var what = e.message || (e.target && (e.target.src || e.target.href)) || "error";
    errors.push("error: " + what + where);
  }, true);
  window.addEventListener("unhandledrejection", function (e) {
    errors.push("unhandled rejection: " + text(e.reason));
  });
  var orig = console.error;
  console.error = function () {
    errors.push("console.error: " + Array.prototype.map.call(arguments, text).join(" "));
    return orig.apply(console, arguments);
  };
})();
