mod common;
use common::*;
use translucent_tof::physics::XiMethod;
use translucent_tof::pipeline::XiChoice;

#[test]
#[ignore]
fn explore() {
    for (xi, alb) in [(0.65, (0.5, 0.7)), (0.94, (0.6, 0.9))] {
        for seed in 1..3 {
            let s = fig5_scene(seed, xi, alb, 2);
            let t = std::time::Instant::now();
            let fixed0 = run_scene(&s, XiChoice::Fixed(xi), 0);
            let fixed = run_scene(&s, XiChoice::Fixed(xi), 4);
            let est = run_scene(&s, XiChoice::Estimate(XiMethod::OneMaterial), 4);
            println!("xi {xi} seed {seed}: raw {:.1} perpixel {:.1} prior {:.1} | est {:.3} [{:.3},{:.3}] rmse {:.1} | {:?} {:?} ({:.1}s)",
                fixed.mean_rmse_raw(), fixed0.mean_rmse(), fixed.mean_rmse(), est.xi, est.interval[0], est.interval[1], est.mean_rmse(), fixed0.frame_rmse_mm, fixed.frame_rmse_mm, t.elapsed().as_secs_f64());
        }
    }
}
