// Shared by the pages: who is acting and REST calls. One name per person: typed in the page header,
// sent as X-Author (percent-encoded UTF-8) with every REST call and mirrored into the slam6d-author cookie, which the 3D view's
// websocket carries, so the buttons in the 3D view act under the same name.
export function authorName() {
  return localStorage.getItem("slam6d-author") || "";
}

function storeAuthorCookie(name) {
  document.cookie = `slam6d-author=${encodeURIComponent(name)}; path=/; SameSite=Strict; max-age=31536000`;
}

export function bindAuthorField(input, onChange = () => {}) {
  input.value = authorName();
  storeAuthorCookie(authorName());
  input.addEventListener("change", () => {
    localStorage.setItem("slam6d-author", input.value.trim());
    storeAuthorCookie(input.value.trim());
    onChange(input.value.trim());
  });
}

// A POST always carries a body: the server takes only JSON (or a form) so that no other site can
// make a browser send one without asking first.
export async function api(path, options = {}) {
  const headers = { ...(options.headers || {}) };
  // header values are Latin-1: the name travels percent-encoded as UTF-8 (RFC 8187), so 张伟 stays 张伟
  if (authorName()) headers["X-Author"] = `UTF-8''${encodeURIComponent(authorName())}`;
  const method = (options.method || "GET").toUpperCase();
  let body = options.body;
  if (method === "POST" && body === undefined) body = "{}";
  if (typeof body === "string") headers["Content-Type"] = "application/json";
  const response = await fetch(path, { ...options, headers, body });
  const text = await response.text();
  let answer = text;
  try { answer = JSON.parse(text); } catch { /* plain text */ }
  if (!response.ok) {
    const detail = answer && answer.detail ? answer.detail : text;
    throw new Error(typeof detail === "string" ? detail : JSON.stringify(detail));
  }
  return answer;
}

// A form that keeps the page: `send` gets the form's fields (and the form); what it throws is shown in
// `errorOut`, so every form reports a refused request the same way.
export function onSubmit(form, errorOut, send) {
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    try { await send(new FormData(form), form); } catch (err) { errorOut.textContent = err.message; }
  });
}

// A header button that opens and closes a panel; opening it refreshes what the panel lists.
export function togglePanel(button, panel, refresh, errorOut) {
  button.onclick = async () => {
    panel.hidden = !panel.hidden;
    if (!panel.hidden) await refresh().catch((err) => { errorOut.textContent = err.message; });
  };
}
