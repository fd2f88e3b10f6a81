"""Regenerate docs/figures/calibration_bias.png and the bias table of docs/calibration.md.

Run from the repository root: .venv/bin/python docs/figures/calibration_bias.py
"""
import sys; sys.path.insert(0,'tests')
import numpy as np, cv2
from test_calibration_camera import synthetic_views, POINTS, calibrate
from reflab.core.workspace import atomic_path
rows=[]
for radius in (0.0035, 0.0050, 0.0065):
    obs, _ = synthetic_views(8, seed=2, noise_rms=0.0, radius=radius, distance=0.2, max_tilt=55.0)
    r_on = calibrate(obs, POINTS, (640, 480), radius=radius).camera
    r_off = calibrate(obs, POINTS, (640, 480), bias_correction=False)
    c_off = r_off.camera
    cv = r_off.crosscheck
    def err(fx, fy, cx, cy): return 100*max(abs(fx/620-1),abs(fy/620-1)), np.hypot(cx-325, cy-236)
    e_on = err(r_on.K[0,0], r_on.K[1,1], r_on.K[0,2], r_on.K[1,2])
    e_off = err(c_off.K[0,0], c_off.K[1,1], c_off.K[0,2], c_off.K[1,2])
    e_cv = err(cv['fx'], cv['fy'], cv['cx'], cv['cy'])
    rows.append((radius, e_on, e_off, e_cv))
    print(f"| {radius*1000:.1f} mm | {e_cv[0]:.4f}% / {e_cv[1]:.3f} px | {e_off[0]:.4f}% / {e_off[1]:.3f} px | {e_on[0]:.5f}% / {e_on[1]:.4f} px |")
# Bar plot: principal-point error per radius, three methods (log-free, px).
W,H=640,360; img=np.full((H,W,3),255,np.uint8)
ymax=max(max(r[2][1],r[3][1]) for r in rows)*1.15
x0,y0,y1=60,320,30
cv2.line(img,(x0,y0),(W-20,y0),(0,0,0),1); cv2.line(img,(x0,y0),(x0,y1),(0,0,0),1)
cols=[(60,60,200),(200,120,40),(40,160,40)]; names=["cv2.calibrateCamera","ours, no correction","ours, bias-corrected"]
for g,(rad,on,off,cvv) in enumerate(rows):
    for k,v in enumerate((cvv[1],off[1],on[1])):
        xa=x0+30+g*180+k*50; h=int((y0-y1)*v/ymax)
        cv2.rectangle(img,(xa,y0-h),(xa+40,y0),cols[k],-1)
        cv2.putText(img,f"{v:.3f}",(xa-2,y0-h-5),cv2.FONT_HERSHEY_SIMPLEX,0.38,(0,0,0),1)
    cv2.putText(img,f"disc radius {rad*1000:.1f} mm",(x0+30+g*180,y0+20),cv2.FONT_HERSHEY_SIMPLEX,0.45,(0,0,0),1)
for k,n in enumerate(names):
    cv2.rectangle(img,(W-230,20+k*20),(W-218,32+k*20),cols[k],-1); cv2.putText(img,n,(W-212,31+k*20),cv2.FONT_HERSHEY_SIMPLEX,0.42,(0,0,0),1)
cv2.putText(img,"principal-point error (px), noise-free, 8 views, tilt <= 55 deg",(x0,18),cv2.FONT_HERSHEY_SIMPLEX,0.45,(0,0,0),1)
with atomic_path('docs/figures/calibration_bias.png') as tmp: cv2.imwrite(str(tmp), img)
