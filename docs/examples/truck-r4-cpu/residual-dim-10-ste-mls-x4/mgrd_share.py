"""Usage: python mgrd_share.py HAC.pgs PREDICT_GS.pgs (run with OMP_NUM_THREADS=1).

Median over 3 rounds of the mean per view on the test views (1 thread): HAC and Predict-GS decoded frames split into
prefilter, decoder MLPs (+ f_c cache gather), MGRD heads, keep+activate, rasterize."""
import sys, time, statistics, torch
sys.path.insert(0, str(__import__('pathlib').Path(__file__).resolve().parents[4]))  # the repository root
from baseline.codec.model_codec import decode_model
from baseline.run import load_scene_for
from baseline.pipeline import visible_anchors
from baseline.render import rasterize
from baseline.train.trainer import set_threads
set_threads(1)
files = sys.argv[1:]
decs = [decode_model(f) for f in files]
sc = load_scene_for(decs[0].cfg, decs[0].scene_path, progress=False)
cams = sc.test_cameras; bg = sc.background.float()
def T(fn):
    t0 = time.perf_counter(); o = fn(); return o, time.perf_counter() - t0
res = {f: {k: [] for k in ('prefilter', 'heads', 'mgrd', 'decode', 'raster', 'frame', 'gs')} for f in files}
torch.set_grad_enabled(False)
for rnd in range(-1, 3):
    order = list(zip(files, decs)) if rnd % 2 == 0 else list(zip(files, decs))[::-1]
    for f, d in order:
        m = d.model
        acc = {k: 0.0 for k in res[f]}
        for cam in cams:
            idx, t_p = T(lambda: visible_anchors(m, cam))
            values = m.coded_values(idx); xyz = m.xyz[idx]
            def heads():
                feat = m.provider.decoder_features(idx, values, xyz)
                view = xyz - cam.center.to(xyz)[None, :]
                dist = view.norm(dim=1, keepdim=True).clamp_min(1e-8)
                return m.decoder(feat, view / dist, dist), view / dist, dist
            (_, vd, dist), t_h = T(heads)
            t_m = 0.0
            if m.refiner is not None and m.refiner.active:
                _, t_m = T(lambda: m.refiner(idx, values, vd, dist))
            g, t_d = T(lambda: m.decode(cam.center, idx))
            _, t_r = T(lambda: rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, cam, background=bg, backend='cpu'))
            for k, v in (('prefilter', t_p), ('heads', t_h), ('mgrd', t_m), ('decode', t_d), ('raster', t_r), ('frame', t_p + t_d + t_r), ('gs', g.means.shape[0])):
                acc[k] += v / len(cams)
        if rnd >= 0:
            for k in acc: res[f][k].append(acc[k])
for f in files:
    r = {k: statistics.median(v) for k, v in res[f].items()}
    print(f, ' '.join(f"{k} {v*1e3:.1f}ms" if k != 'gs' else f"gs {v:,.0f}" for k, v in r.items()))
f0, f1 = files[0], files[-1]
m0 = {k: statistics.median(v) for k, v in res[f0].items()}; m1 = {k: statistics.median(v) for k, v in res[f1].items()}
print('frame ratio (ref/other) %.3f' % (m0['frame'] / m1['frame']))
print('ratio if the MGRD heads cost nothing: %.3f' % (m0['frame'] / (m1['frame'] - m1['mgrd'])))
