// One-line status texts: their full text in their tooltip.
//
// Live text above a canvas (a robot's state beside its name, the scene's fixed frame, the
// header's identity) is kept to one line cut with an ellipsis (css/app.css, `.oneline`):
// a line that wrapped as its text grew moved the map under an operator's pointer between
// the aim and the press, and a goal went out ~0.5 m off. What the ellipsis hides stays
// readable in the element's title, kept equal to its text here, whoever wrote the text.

/**
 * Keep the title of every `.oneline` element under *root* equal to its text.
 * @param {Element} root the subtree to watch (the page's body)
 * @returns {MutationObserver} the observer (disconnect it to stop)
 */
export function mirrorTitles(root) {
  const sync = () => {
    for (const el of root.querySelectorAll(".oneline")) {
      const text = el.textContent.trim();
      if (el.title !== text) el.title = text;
    }
  };
  // Only text and child changes: setting a title (an attribute) does not call sync again.
  const observer = new MutationObserver(sync);
  observer.observe(root, { childList: true, characterData: true, subtree: true });
  sync();
  return observer;
}
