<script>
window.__errors = [];
(function () {
  const error = console.error;
  console.error = function (...args) { window.__errors.push(args.join(" ")); error.apply(console, args); };
  window.addEventListener("error", e => window.__errors.push(String(e.message || (e.target && e.target.src ? "failed to load " + e.target.tagName : "error"))), true);
  window.addEventListener("load", () => {
    const root = document.documentElement, width = root.clientWidth;
    const imgs = [...document.images];
    const r = {
      images: imgs.length,
      broken: imgs.filter(i => !(i.complete && i.naturalWidth > 0)).length,
      scroll_width: root.scrollWidth, client_width: width,
      overflowing: [...document.body.querySelectorAll("*")].filter(e => e.getBoundingClientRect().right > width + 1).map(e => e.tagName),
      errors: window.__errors,
      tables: [...document.querySelectorAll("table")].map(t => [...t.rows].map(r => [...r.cells].map(c => c.textContent))),
    };
    const pre = document.createElement("pre");
    pre.id = "mocap-check"; pre.style.display = "none"; pre.textContent = JSON.stringify(r);
    document.body.appendChild(pre);
  });
})();
</script>
