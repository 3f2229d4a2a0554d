// A charts panel (machine page; one per machine on the compare page): the channel picker (any stored or derived channel, one chart
// per unit) and the load history of the replay view, drawn by charts.js on the one time cursor.
import { channelCatalog, chartGroups, DEFAULT_KINDS } from "./charts.js";

export class ChartPanel {
  // source: the page's data source; model: the machine description (/model); els: {list,
  // count, charts, msg} elements; wanted: channel names asked for by the link (`ch=`); kinds:
  // the channel kinds charted when nothing is asked for.
  constructor(source, model, els, wanted, kinds = DEFAULT_KINDS) {
    this.source = source;
    this.els = els;
    this.kinds = kinds;
    this.catalog = channelCatalog(model);
    const ok = wanted.filter((n) => this.catalog.some((c) => c.name === n));
    this.selected = ok.length ? ok : this.defaults();
    this.charts = null;
    this.groups = null;
    this.ask = 0;
  }

  defaults() { return this.catalog.filter((c) => this.kinds.includes(c.kind)).map((c) => c.name); }

  // A raw channel (a pressure if there is one): where it has buckets, the machine sent samples
  // (derived channels only reach as far as the twin worker has processed).
  coverageChannel() {
    const c = this.catalog.find((x) => x.kind === "pressure") || this.catalog[0];
    return c ? c.name : "payload";
  }

  // The picker's checkboxes, grouped by kind; onPick() after the user changed the choice.
  buildPicker(onPick) {
    const box = this.els.list;
    box.innerHTML = "";
    const kinds = [];
    for (const c of this.catalog) if (!kinds.includes(c.kind)) kinds.push(c.kind);
    for (const k of kinds) {
      const fs = document.createElement("fieldset");
      const chans = this.catalog.filter((c) => c.kind === k);
      fs.innerHTML = `<legend>${chans[0].title}</legend>`;
      for (const c of chans) {
        const label = document.createElement("label");
        const input = document.createElement("input");
        input.type = "checkbox";
        input.value = c.name;
        input.dataset.channel = c.name;
        input.checked = this.selected.includes(c.name);
        input.onchange = () => { this.readPicker(); onPick(); };
        label.append(input, ` ${c.label}${c.live ? "" : " (not live)"}`);
        fs.appendChild(label);
      }
      box.appendChild(fs);
    }
    this.els.count.textContent = String(this.selected.length);
  }

  readPicker() {
    this.selected = [...this.els.list.querySelectorAll("input:checked")].map((i) => i.value);
    this.els.count.textContent = String(this.selected.length);
    if (!this.charts) return;
    this.groups = chartGroups(this.catalog, this.selected);
    this.charts.setGroups(this.groups);
  }

  // Creates the charts (plotly is loaded by then): make(groups) -> a Charts object.
  attach(make) {
    this.groups = chartGroups(this.catalog, this.selected);
    this.charts = make(this.groups);
  }

  // Min/max history of the charted channels over [from, to]; events() and cursor() are read
  // when the answer arrives. Resolves to true when this answer was drawn (not overtaken).
  async loadHistory(from, to, events, cursor) {
    if (!this.charts) return false;
    const channels = this.groups.flatMap((g) => g.channels);
    const msg = this.els.msg;
    if (channels.length === 0) {
      this.charts.setHistory({ channels: {} }, events());
      msg.hidden = false; msg.textContent = "No channel chosen: pick some under Channels.";
      return false;
    }
    const ask = ++this.ask;
    let drawn = false;
    try {
      const maxPoints = Math.min(2000, Math.max(200, Math.round(this.els.charts.clientWidth * 1.5)));
      const hist = await this.source.history(from, to, channels, maxPoints);
      if (ask !== this.ask) return false; // a newer view or channel choice asked meanwhile
      const any = this.charts.setHistory(hist, events());
      drawn = true;
      msg.hidden = any;
      if (!any) msg.textContent = "No load history in this range.";
    } catch (err) {
      msg.hidden = false;
      msg.textContent = `Load history unavailable: ${err.message}`;
    }
    this.charts.setCursor(cursor());
    return drawn;
  }
}
