// GPS panel: sensor_msgs/msg/NavSatFix on a Leaflet map (Debian libjs-leaflet) with no
// tile layer (no tile server is reachable), the track as a polyline; a text readout if
// Leaflet is missing.

const MAX_TRACK = 2000; // fixes kept on the track (oldest dropped)

export class GpsView {
  constructor(el, readout, vendorBase = "vendor/") {
    this.el = el;
    this.readout = readout;
    this.track = [];
    this.latest = null;
    this.ready = this.init(vendorBase);
  }

  async init(vendorBase) {
    try {
      const L = await import(new URL(`${vendorBase}leaflet/leaflet.esm.js`, document.baseURI).href);
      this.L = L;
      this.map = L.map(this.el, { attributionControl: false, zoomControl: true }).setView([0, 0], 2);
      this.line = L.polyline([], { color: "#29b6f6" }).addTo(this.map);
      // The dot is added with the first fix: no marker at (0, 0) before one exists.
      this.dot = L.circleMarker([0, 0], { radius: 7, color: "#ffca28", fillOpacity: 0.9 });
    } catch (err) {
      this.el.textContent = `Leaflet unavailable (${err.message}); showing coordinates only.`;
    }
  }

  update(msg) {
    this.latest = msg;
  }

  /** Another robot's page: its track is not the last one's. */
  reset() {
    this.latest = null;
    this.track = [];
    this.readout.textContent = "no fix yet";
    this.line?.setLatLngs([]);
    if (this.map?.hasLayer(this.dot)) this.dot.remove();
  }

  render() {
    const msg = this.latest;
    if (!msg) return;
    this.latest = null;
    const fix = msg.status.status >= 0;
    this.readout.textContent = `${msg.latitude.toFixed(6)}, ${msg.longitude.toFixed(6)}  alt ${msg.altitude.toFixed(1)} m  ${fix ? "fix" : "NO FIX"}`;
    if (!fix || !this.map) return;
    const ll = [msg.latitude, msg.longitude];
    this.track.push(ll);
    if (this.track.length > MAX_TRACK) this.track.shift();
    this.line.setLatLngs(this.track);
    this.dot.setLatLng(ll);
    if (!this.map.hasLayer(this.dot)) this.dot.addTo(this.map);
    if (this.track.length === 1) this.map.setView(ll, 18);
    else if (!this.map.getBounds().contains(ll)) this.map.panTo(ll);
  }
}
