use super::*;

fn repo_file(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(name)
}

#[test]
fn shipped_config_lists_the_built_in_defaults() {
    let path = repo_file("config/spinscand.toml");
    assert_eq!(Config::load(&path).unwrap(), Config::default(), "config/spinscand.toml and Config::default() disagree");
    // Every key is written out (the optional camera controls commented): the file's
    // keys are the defaults' keys.
    let file: toml::Table = toml::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let defaults: toml::Table = toml::from_str(&toml::to_string(&Config::default()).unwrap()).unwrap();
    let keys = |t: &toml::Table| -> Vec<String> { t.iter().flat_map(|(s, v)| v.as_table().unwrap().keys().map(move |k| format!("{s}.{k}"))).collect() };
    assert_eq!(keys(&file), keys(&defaults), "config/spinscand.toml must write out every key");
}

#[test]
fn sim_config_is_the_sim_defaults() {
    assert_eq!(Config::load(&repo_file("config/sim.toml")).unwrap(), Config::sim());
}

#[test]
fn bad_values_are_named() {
    let p = Path::new("x.toml");
    let e = Config::parse(p, "[cameras]\npixel_format = \"RGB3\"\n").unwrap_err().to_string();
    assert!(e.contains("cameras.pixel_format") && e.contains("MJPG"), "{e}");
    let e = Config::parse(p, "[scan]\nstep_degs = 2\n").unwrap_err().to_string();
    assert!(e.contains("step_degs"), "{e}");
    let e = Config::parse(p, "[daemon]\nsocket_mode = \"rw\"\n").unwrap_err().to_string();
    assert!(e.contains("socket_mode"), "{e}");
    let e = Config::parse(p, "[backend]\nkind = \"replay\"\n").unwrap_err().to_string();
    assert!(e.contains("backend.replay"), "{e}");
    let e = Config::parse(p, "[matching]\nassist = \"sometimes\"\n").unwrap_err().to_string();
    assert!(e.contains("matching.assist"), "{e}");
    let e = Config::parse(p, "[matching]\nassist_granularity = \"block\"\n").unwrap_err().to_string();
    assert!(e.contains("matching.assist_granularity") && e.contains("expected auto, pixel, tile or plane"), "{e}");
    for text in ["blue", "0,0,256", "1,2"] {
        let e = Config::parse(p, &format!("[matching]\nkey_color = \"{text}\"\n")).unwrap_err().to_string();
        assert!(e.contains("matching.key_color") && e.contains("expected `auto` or R,G,B"), "{text}: {e}");
    }
    let e = Config::parse(p, "[matching]\nplate = \"/no/such/plate.png\"\n").unwrap_err().to_string();
    assert!(e.contains("matching.plate") && e.contains("/no/such/plate.png") && e.contains("empty scene"), "{e}");
    let plate = std::env::temp_dir().join(format!("spinscan-config-plate-{}.png", std::process::id()));
    crate::io::write_rgb_png(&plate, 3, 2, &[90; 18]).unwrap();
    let c = Config::parse(p, &format!("[matching]\nplate = \"{}\"\n", plate.display())).unwrap();
    let loaded = c.pipeline_settings().plate.expect("the plate");
    assert_eq!((loaded.width, loaded.height, loaded.rgb.len()), (3, 2, 18));
    assert!(Config::default().pipeline_settings().plate.is_none());
    std::fs::remove_file(&plate).unwrap();
    let c = Config::parse(p, "[matching]\nkey_color = \"0, 71, 187\"\n").unwrap();
    assert_eq!(c.pipeline_settings().pipeline.chroma.key, crate::segment::KeyColour::Rgb([0, 71, 187]));
    assert_eq!(Config::default().pipeline_settings().pipeline.chroma.key, crate::segment::KeyColour::Auto);
    let e = Config::parse(p, "[matching]\nrim_px = 33\n").unwrap_err().to_string();
    assert!(e.contains("matching.rim_px") && e.contains("expected 0 … 32 pixels, got 33"), "{e}");
    let e = Config::parse(p, "[matching]\nrim_px = -1\n").unwrap_err().to_string();
    assert!(e.contains("rim_px"), "{e}");
    let rim = |text: &str| Config::parse(p, text).unwrap().pipeline_settings().pipeline.chroma.rim_px;
    assert_eq!((rim("[matching]\nrim_px = 0\n"), rim("")), (0, crate::segment::DEFAULT_RIM_PX));
}

#[test]
fn matcher_parameters_follow_the_matchers_rules_and_every_accepted_value_builds() {
    let p = Path::new("x.toml");
    for (text, key) in [("p1 = 0", "matching.p1"), ("p2 = 9000", "matching.p2"), ("sgm_paths = 6", "matching.sgm_paths"), ("sgm_ad_cap = 101", "matching.sgm_ad_cap"), ("method = \"census\"", "expected `bm` or `sgm`"), ("block = 33", "matching.block"), ("block = 4", "matching.block"), ("block = 1", "matching.block"), ("sgm_refine_block = 8", "matching.sgm_refine_block"), ("sgm_refine_block = 33", "matching.sgm_refine_block"), ("sgm_refine_agree = 0.05", "matching.sgm_refine_agree"), ("sgm_refine_agree = 2.5", "matching.sgm_refine_agree"), ("num_disparities = 0", "matching.num_disparities"), ("num_disparities = 2000", "matching.num_disparities"), ("coarse_to_fine = \"maybe\"", "coarse_to_fine = \"maybe\": expected \"auto\", \"on\", \"off\", true or false"), ("coarse_to_fine = 1", "coarse_to_fine: expected \"auto\"")] {
        let e = Config::parse(p, &format!("[matching]\n{text}\n")).unwrap_err().to_string();
        assert!(e.contains(key), "{text}: {e}");
    }
    // The bounds of what is accepted: each builds the pipeline a scan starts with.
    let calib = crate::hw::sim::ideal_calib(64, 48, 70.0, 60.0);
    for (block, n) in [(3, 1), (31, 1), (31, 1024), (9, 100), (3, 1024)] {
        let c = Config::parse(p, &format!("[matching]\nblock = {block}\nnum_disparities = {n}\n")).unwrap_or_else(|e| panic!("block {block}, {n} disparities: {e}"));
        let settings = c.pipeline_settings();
        crate::pipeline::Pipeline::new(&calib, (64, 48), settings.pipeline).unwrap_or_else(|e| panic!("block {block}, {n} disparities: {e}"));
    }
    let c = Config::parse(p, "[matching]\nmethod = \"sgm\"\np1 = 7\np2 = 2000\nsgm_paths = 8\n").unwrap();
    let m = c.pipeline_settings().pipeline.matching;
    assert_eq!((m.method, m.p1, m.p2, m.sgm_paths, m.uniqueness_ratio), (crate::stereo::Method::Sgm, 7, 2000, 8, 0));
    // `coarse_to_fine`: the method's default unless said.
    for (text, seed) in [("method = \"sgm\"", true), ("method = \"bm\"", false), ("method = \"sgm\"\ncoarse_to_fine = \"off\"", false), ("method = \"bm\"\ncoarse_to_fine = \"on\"", true), ("method = \"bm\"\ncoarse_to_fine = true", true)] {
        let c = Config::parse(p, &format!("[matching]\n{text}\n")).unwrap();
        assert_eq!(c.pipeline_settings().pipeline.matching.coarse_to_fine, seed, "{text}");
    }
}

#[test]
fn scan_bounds_are_the_socket_bounds() {
    let p = Path::new("x.toml");
    for text in ["step_deg = 0", "step_deg = 361", "total_deg = 3601", "total_deg = -5"] {
        let e = Config::parse(p, &format!("[scan]\n{text}\n")).unwrap_err().to_string();
        let key = text.split(' ').next().unwrap();
        assert!(e.contains(&format!("scan.{key}")), "{text}: {e}");
    }
}
