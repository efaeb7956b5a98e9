# One call on the lent H100 (session 28): python3 .../stages.py 1-hac+ste+mls-l0.004.pgs 2-pgs-r10+ste+mls-l0.004.pgs
# (after source tools/device_setup.sh; cameras .carry/cams.pt = the 32 truck -r 4 test views)
import sys, time, torch
from dataclasses import replace
sys.path.insert(0, '.')
from baseline.camera import Camera
from baseline.codec.model_codec import decode_model
from baseline.pipeline import visible_anchors
from baseline.render import rasterize
blob = torch.load('.carry/cams.pt', weights_only=True)
cams0 = [Camera(**c) for c in blob['cameras']]
bg = blob['background'].cuda()
models = {}
for f in sys.argv[1:]:
    m = decode_model(f).model.to('cuda'); m.bake(); models[f.split('/')[-1]] = m
S = torch.cuda.synchronize
for k in (4, 1):
    cams = [replace(c, fx=c.fx*k, fy=c.fy*k, cx=c.cx*k, cy=c.cy*k, width=c.width*k, height=c.height*k) for c in cams0]
    res = {n: {s: [] for s in ('prefilter', 'decode_plain', 'decode_baked', 'raster')} for n in models}
    for r in range(-1, 10):
        for n, m in models.items():
            acc = dict.fromkeys(res[n], 0.0)
            with torch.no_grad():
                for cam in cams:
                    S(); t0 = time.perf_counter(); idx = visible_anchors(m, cam); S(); t1 = time.perf_counter()
                    g = m.decode(cam.center, idx); S(); t2 = time.perf_counter()
                    g = m.baked.decode(cam.center, idx); S(); t3 = time.perf_counter()
                    rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, cam, background=bg, backend='auto'); S(); t4 = time.perf_counter()
                    for s, d in zip(res[n], (t1-t0, t2-t1, t3-t2, t4-t3)): acc[s] += d / len(cams)
            if r >= 0:
                for s in acc: res[n][s].append(acc[s])
    print(f"scale {k} ({cams[0].width}x{cams[0].height}): ms/view, median of 10 rounds")
    for n in models:
        print(f"  {n:34s}" + "  ".join(f"{s} {1000*sorted(v)[5]:.3f}" for s, v in res[n].items()))
