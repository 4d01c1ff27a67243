// GPS panel: sensor_msgs/msg/NavSatFix on a Leaflet map (Debian libjs-leaflet) with no
// tile layer (no tile server is reachable), the track as a polyline; a text readout if
// Leaflet is missing.

const MAX_TRACK = 2000; // fixes kept on the track (oldest dropped)
// sensor_msgs/msg/NavSatStatus.status, in words.
const FIX_KIND = { [-1]: "NO FIX", 0: "fix", 1: "SBAS fix", 2: "GBAS (RTK) fix" };

/**
 * A NavSatFix in words with units: "lat 30.286200° lon -97.736500° alt 150.0 m, fix,
 * ±1.5 m". The accuracy is the larger horizontal standard deviation of a known or
 * approximated covariance (position_covariance_type > 0); none when unknown.
 */
export function fixText(msg) {
  const kind = FIX_KIND[msg.status.status] ?? `status ${msg.status.status}`;
  const cov = msg.position_covariance;
  const sigma = msg.position_covariance_type > 0 && cov ? Math.sqrt(Math.max(cov[0], cov[4])) : NaN;
  const accuracy = Number.isFinite(sigma) ? `, ±${sigma.toFixed(1)} m` : "";
  return `lat ${msg.latitude.toFixed(6)}° lon ${msg.longitude.toFixed(6)}° alt ${msg.altitude.toFixed(1)} m, ${kind}${accuracy}`;
}

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
      // No tiles (no tile server is reachable): the scale is the only sense of distance.
      L.control.scale({ imperial: false, position: "bottomleft" }).addTo(this.map);
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
    this.readout.textContent = fixText(msg);
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
