//! A prepared association run: inputs checked, visibility resolved, depth renderer ready; the
//! view pairs' directed overlaps and the grouping of their evidence into proposals.

use super::*;

/// A prepared run: inputs checked, visibility resolved, depth renderer ready.
pub struct Association<'a> {
    pub(super) frame: Frame<'a>,
    pub(super) params: Params,
    pub(super) visibility: Visibility,
    pub(super) depth: Option<DepthCache<'a>>,
    /// The Gaussians (points of the consensus grouping).
    pub(super) gaussians: Option<&'a Gaussians>,
    /// The grouping in use (never `Auto`).
    pub(super) grouping: Grouping,
    /// The scene bounds of the extents, when the extent rules run.
    pub(super) bounds: Option<Bounds>,
    /// Per view, its masks' extents once computed (empty without `bounds`).
    pub(super) view_extents: Vec<OnceLock<Vec<extent::Extent>>>,
}

impl std::fmt::Debug for Association<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Association")
            .field("params", &self.params)
            .field("visibility", &self.visibility)
            .finish_non_exhaustive()
    }
}

/// One unordered view pair and the rows of its two warps.
#[derive(Debug, Clone, Copy)]
pub(super) struct ViewPair {
    pub(super) i: usize,
    pub(super) j: usize,
    pub(super) forward: Option<usize>,
    pub(super) backward: Option<usize>,
}

#[derive(Debug, Default)]
pub(crate) struct PairResult {
    pub(crate) links: graph::PairLinks,
    pub(crate) cells: CellCounts,
    pub(crate) skipped: bool,
}

impl<'a> Association<'a> {
    /// Checks the inputs against each other and the parameters, and resolves
    /// [`Visibility::Auto`].
    pub fn new(inputs: Inputs<'a>, params: &Params) -> Result<Self> {
        params.validate()?;
        let frame = Frame::new(inputs.masks, inputs.matches, inputs.cameras)?;
        let visibility = match params.visibility {
            Visibility::Auto if inputs.cameras.is_some() && inputs.gaussians.is_some() => {
                Visibility::Both
            }
            Visibility::Auto => Visibility::FwdBwd,
            v => v,
        };
        if visibility.uses_depth() && (inputs.cameras.is_none() || inputs.gaussians.is_none()) {
            return Err(WarpGraphError::MissingGaussians {
                what: "the depth visibility test",
            });
        }
        let grouping = match params.grouping {
            Grouping::Auto if inputs.cameras.is_some() && inputs.gaussians.is_some() => {
                Grouping::Consensus
            }
            Grouping::Auto => Grouping::Links,
            g => g,
        };
        let extent_rules = grouping == Grouping::Links
            && params.same_view_support.is_some()
            && (params.extent_agreement.is_some() || params.extent_merge_iou.is_some());
        let bounds = match inputs.gaussians {
            Some(g) if extent_rules && inputs.cameras.is_some() => Bounds::from_points(&g.means),
            _ => None,
        };
        let consensus = grouping == Grouping::Consensus;
        if consensus && (inputs.cameras.is_none() || inputs.gaussians.is_none()) {
            return Err(WarpGraphError::MissingGaussians {
                what: "the view-consensus grouping",
            });
        }
        let depth = if visibility.uses_depth() || bounds.is_some() {
            let (Some(cameras), Some(gaussians)) = (inputs.cameras, inputs.gaussians) else {
                return Err(WarpGraphError::MissingGaussians {
                    what: "the depth visibility test",
                });
            };
            let raster = Rasterizer::new(gaussians).map_err(|source| WarpGraphError::Raster {
                context: "preparing the Gaussians for depth rendering".into(),
                source,
            })?;
            Some(DepthCache::new(
                raster,
                cameras,
                frame.gw,
                frame.gh,
                params.depth_min_alpha,
                params.depth_cache_views,
            ))
        } else {
            None
        };
        let view_extents = if bounds.is_some() {
            (0..frame.masks.num_views())
                .map(|_| OnceLock::new())
                .collect()
        } else {
            Vec::new()
        };
        Ok(Association {
            frame,
            params: *params,
            visibility,
            depth,
            gaussians: inputs.gaussians,
            grouping,
            bounds,
            view_extents,
        })
    }

    /// The occlusion test in use (never `Auto`).
    pub fn visibility(&self) -> Visibility {
        self.visibility
    }

    /// The grouping in use (never `Auto`).
    pub fn grouping(&self) -> Grouping {
        self.grouping
    }

    /// The overlaps of one directed warp (row `row` of the matches' `pairs`).
    pub fn directed_overlaps(&self, row: usize) -> Result<DirectedOverlaps> {
        let Some(&[i, j]) = self.frame.matches.pairs.get(row) else {
            return Err(WarpGraphError::InvalidParameter {
                name: "row",
                value: row.to_string(),
                expected: "a row of the matches' `pairs`",
            });
        };
        let (i, j) = (i as usize, j as usize);
        let (pi, pj) = (self.frame.label_plane(i)?, self.frame.label_plane(j)?);
        self.directed(row, i, j, &pi, &pj)
    }

    /// Runs Algorithm 1 over every view pair; `progress(done, total)` is called after each
    /// view pair (from worker threads, in any order).
    pub fn run(&self, progress: &(dyn Fn(usize, usize) + Sync)) -> Result<Outcome> {
        let evidence = self.pair_evidence(0..self.num_view_pairs(), progress)?;
        self.group(&evidence)
    }

    /// The number of unordered view pairs, T: [`Association::pair_evidence`] takes ranges
    /// of `0..T`.
    pub fn num_view_pairs(&self) -> usize {
        self.view_pairs().len()
    }

    /// The unordered view pairs (i < j) in the order that ranges of
    /// [`Association::pair_evidence`] index.
    pub fn view_pair_ids(&self) -> Vec<[u32; 2]> {
        self.view_pairs()
            .iter()
            .map(|p| [p.i as u32, p.j as u32])
            .collect()
    }

    /// The mask-pair evidence (accepted links and counters) of view pairs `range` of
    /// [`Association::view_pair_ids`]; `progress(done, total)` is called after each pair.
    /// Evidence of consecutive ranges concatenated ([`Evidence::merge`]) equals the
    /// evidence of their union, so a run split into ranges groups into the same proposals.
    pub fn pair_evidence(
        &self,
        range: std::ops::Range<usize>,
        progress: &(dyn Fn(usize, usize) + Sync),
    ) -> Result<Evidence> {
        let all = self.view_pairs();
        let Some(pairs) = all.get(range.clone()) else {
            return Err(WarpGraphError::InvalidParameter {
                name: "pairs",
                value: format!("{}..{}", range.start, range.end),
                expected: "a range of the run's view pairs (0..T)",
            });
        };
        let done = AtomicUsize::new(0);
        let results: Vec<Result<PairResult>> = pairs
            .par_iter()
            .map(|vp| {
                let r = self.pair_job(vp);
                progress(done.fetch_add(1, Ordering::Relaxed) + 1, pairs.len());
                r
            })
            .collect();
        let mut evidence = Evidence::empty(range.start);
        for (vp, r) in pairs.iter().zip(results) {
            evidence.push_pair([vp.i as u32, vp.j as u32], &r?);
        }
        Ok(evidence)
    }

    /// Groups the masks from the evidence of every view pair (one run's, or shards' merged
    /// in view-pair order) into proposals.
    pub fn group(&self, evidence: &Evidence) -> Result<Outcome> {
        let pairs = self.view_pairs();
        if evidence.first_pair != 0 || evidence.pairs != self.view_pair_ids() {
            return Err(WarpGraphError::InvalidParameter {
                name: "evidence",
                value: format!(
                    "view pairs {}..{} ({} pairs)",
                    evidence.first_pair,
                    evidence.first_pair + evidence.pairs.len(),
                    evidence.pairs.len()
                ),
                expected: "the evidence of every view pair of these masks and matches, in order",
            });
        }
        let edges = evidence.edges.clone();
        let (cells, rejections) = (evidence.cells, evidence.rejections);
        let (tested, skipped) = (evidence.tested, evidence.skipped as usize);
        let masks = self.frame.masks;
        let (extents, proposals, components, consensus) = match self.grouping {
            Grouping::Links | Grouping::Auto => {
                let extents = self.mask_extents()?;
                let (p, c) = graph::proposals_from_links(
                    &masks.mask_offsets,
                    &edges,
                    &self.params,
                    extents.as_ref(),
                    self.metadata(),
                );
                (extents.is_some(), p, c, None)
            }
            Grouping::Consensus => {
                let (p, c, s) = self.consensus_proposals(&edges)?;
                (false, p, c, Some(s))
            }
        };
        let report = Report {
            views: masks.num_views(),
            masks: masks.num_masks(),
            pairs: self.frame.matches.pairs.len(),
            view_pairs: pairs.len(),
            one_direction_pairs: pairs
                .iter()
                .filter(|p| p.forward.is_none() || p.backward.is_none())
                .count(),
            skipped_pairs: skipped,
            grid: [self.frame.gw, self.frame.gh],
            mask_grid: [self.frame.mw, self.frame.mh],
            visibility: self.visibility.name(),
            sampling: self.params.sampling.name(),
            extents,
            cells,
            edges_tested: tested,
            edges_accepted: edges.len() as u64,
            rejections,
            grouping: self.grouping.name(),
            consensus,
            components,
        };
        Ok(Outcome {
            proposals,
            edges,
            report,
        })
    }

    /// The proposals of the view-consensus grouping: every point labelled in every view
    /// (views in parallel, collected in view order), then the clustering.
    pub(super) fn consensus_proposals(
        &self,
        links: &[Link],
    ) -> Result<(Proposals, ComponentStats, ConsensusStats)> {
        let f = &self.frame;
        let (Some(cameras), Some(gaussians)) = (f.cameras, self.gaussians) else {
            return Err(WarpGraphError::MissingGaussians {
                what: "the view-consensus grouping",
            });
        };
        let cp = &self.params.consensus;
        let n = gaussians.len();
        let stride = consensus::point_stride(n, cp.max_points);
        // The depth test's rasterizer when there is one: the Gaussians are prepared once.
        let own;
        let raster = match &self.depth {
            Some(cache) => cache.raster(),
            None => {
                own = Rasterizer::new(gaussians).map_err(|source| WarpGraphError::Raster {
                    context: "preparing the Gaussians for the top-1 renders".into(),
                    source,
                })?;
                &own
            }
        };
        let opts = RenderOptions {
            color: false,
            depth: DepthMode::None,
            alpha: false,
            transmittance: false,
            top_k: Some(1),
            background: [0.0; 3],
        };
        // Views one after another: each render is itself parallel over tiles.
        let offsets = &f.masks.mask_offsets;
        let mut labels: Vec<Vec<u32>> = Vec::with_capacity(f.masks.num_views());
        let mut mask_points = consensus::MaskPoints::new(f.masks.num_masks(), cp.point_weight);
        let mut out = ViewRender::default();
        for v in 0..f.masks.num_views() {
            let plane = f.label_plane(v)?;
            let cam = grid_camera(cameras, v, f.mw, f.mh)?;
            raster
                .render_camera_into(&cam, v, &opts, &mut out)
                .map_err(|source| WarpGraphError::Raster {
                    context: format!("rendering the top-1 contributors of view {v}"),
                    source,
                })?;
            let ids = out.topk_ids().unwrap_or(&[]);
            let seen = consensus::view_point_labels(ids, &plane, f.mw, n, stride);
            mask_points.add_view(offsets[v], &seen);
            labels.push(seen.labels);
        }
        let points = n.div_ceil(stride);
        let found = consensus::cluster(&labels, &mask_points, offsets, points, links, cp);
        let view_of = graph::views_of_masks(offsets);
        let (mut p, c) = graph::proposals_from_roots(
            &view_of,
            &found.root,
            &found.under,
            &self.params,
            ComponentStats::default(),
            self.metadata(),
        );
        p.mask_share = Some(found.share.into());
        p.mask_instance = Some(graph::instances(&p.mask_proposal, &found.attached).into());
        Ok((p, c, found.stats))
    }

    /// Every mask's 3D extent when the extent rules run (views in parallel, collected in
    /// view order).
    pub(super) fn mask_extents(&self) -> Result<Option<MaskExtents>> {
        let Some(bounds) = &self.bounds else {
            return Ok(None);
        };
        let f = &self.frame;
        // Views that no pair job reached (in no pair, or skipped) are done here.
        (0..f.masks.num_views())
            .into_par_iter()
            .try_for_each(|v| self.ensure_view_extents(v, None))?;
        let mut extents = Vec::with_capacity(f.masks.num_masks());
        for cell in &self.view_extents {
            extents.extend_from_slice(cell.get().map_or(&[][..], Vec::as_slice));
        }
        Ok(Some(MaskExtents {
            extents,
            pad: bounds.padding(self.params.extent_pad),
        }))
    }

    /// Computes view `v`'s mask extents once (label plane given or read), while its depth
    /// map is likely still in the cache from the visibility test. Two threads may compute
    /// the same view; the results are identical and the first one is kept.
    pub(super) fn ensure_view_extents(&self, v: usize, labels: Option<&[u32]>) -> Result<()> {
        let (Some(bounds), Some(cache), Some(cameras), Some(cell)) = (
            &self.bounds,
            &self.depth,
            self.frame.cameras,
            self.view_extents.get(v),
        ) else {
            return Ok(());
        };
        if cell.get().is_some() {
            return Ok(());
        }
        let f = &self.frame;
        let read;
        let labels = match labels {
            Some(l) => l,
            None => {
                read = f.label_plane(v)?;
                &read
            }
        };
        let depth = cache.get(v)?;
        let cam = grid_camera(cameras, v, f.gw, f.gh)?;
        let extents = extent::view_extents(
            labels,
            f.masks.masks_in_view(v),
            &depth,
            (f.gw, f.gh, f.mw),
            &f.xmap,
            &f.ymap,
            &cam,
            bounds,
        );
        let _ = cell.set(extents);
        Ok(())
    }

    /// The parameters, as the proposals file records them.
    pub(super) fn metadata(&self) -> BTreeMap<String, String> {
        let p = &self.params;
        let mut m = BTreeMap::from([
            (
                "generator".to_string(),
                concat!("warp-graph ", env!("CARGO_PKG_VERSION")).to_string(),
            ),
            ("tau_alpha".to_string(), p.tau_alpha.to_string()),
            ("tau_iou".to_string(), p.tau_iou.to_string()),
            ("tau_box".to_string(), p.tau_box.to_string()),
            ("s_min".to_string(), p.s_min.to_string()),
            ("v_min".to_string(), p.v_min.to_string()),
            ("visibility".to_string(), self.visibility.name().to_string()),
            ("sampling".to_string(), p.sampling.name().to_string()),
            ("depth_tolerance".to_string(), p.depth_tolerance.to_string()),
            (
                "fwd_bwd_tolerance".to_string(),
                p.fwd_bwd_tolerance.to_string(),
            ),
            (
                "require_both_warps".to_string(),
                p.require_both_warps.to_string(),
            ),
            (
                "same_view_support".to_string(),
                p.same_view_support
                    .map_or_else(|| "none".to_string(), |s| s.to_string()),
            ),
            (
                "extent_agreement".to_string(),
                p.extent_agreement
                    .map_or_else(|| "none".to_string(), |s| s.to_string()),
            ),
            (
                "extent_merge_iou".to_string(),
                p.extent_merge_iou
                    .map_or_else(|| "none".to_string(), |s| s.to_string()),
            ),
            ("extent_trim".to_string(), p.extent_trim.to_string()),
            ("extent_pad".to_string(), p.extent_pad.to_string()),
            ("extents".to_string(), self.bounds.is_some().to_string()),
        ]);
        // Only the consensus grouping adds keys, so files of the link grouping keep their
        // bytes.
        if self.grouping == Grouping::Consensus {
            let c = &p.consensus;
            m.extend([
                ("grouping".to_string(), self.grouping.name().to_string()),
                (
                    "consensus_visible_ratio".to_string(),
                    c.visible_ratio.to_string(),
                ),
                (
                    "consensus_observed_points".to_string(),
                    c.observed_points.to_string(),
                ),
                (
                    "consensus_contained_ratio".to_string(),
                    c.contained_ratio.to_string(),
                ),
                (
                    "consensus_undersegment_ratio".to_string(),
                    c.undersegment_ratio.to_string(),
                ),
                (
                    "consensus_own_view_votes".to_string(),
                    c.own_view_votes.to_string(),
                ),
                ("consensus_threshold".to_string(), c.consensus.to_string()),
                (
                    "consensus_union_ratio".to_string(),
                    c.union_ratio.to_string(),
                ),
                ("consensus_max_points".to_string(), c.max_points.to_string()),
                ("consensus_link_merge".to_string(), c.link_merge.to_string()),
                (
                    "consensus_point_weight".to_string(),
                    c.point_weight.name().to_string(),
                ),
            ]);
        }
        m
    }

    /// Unordered view pairs in (i, j) order, i < j.
    pub(super) fn view_pairs(&self) -> Vec<ViewPair> {
        let mut keys: Vec<(u32, u32)> = self
            .frame
            .pair_index
            .keys()
            .map(|&(i, j)| (i.min(j), i.max(j)))
            .collect();
        keys.sort_unstable();
        keys.dedup();
        keys.into_iter()
            .map(|(i, j)| ViewPair {
                i: i as usize,
                j: j as usize,
                forward: self.frame.pair_index.get(&(i, j)).copied(),
                backward: self.frame.pair_index.get(&(j, i)).copied(),
            })
            .collect()
    }

    pub(super) fn pair_job(&self, vp: &ViewPair) -> Result<PairResult> {
        if self.params.require_both_warps && (vp.forward.is_none() || vp.backward.is_none()) {
            return Ok(PairResult {
                skipped: true,
                ..PairResult::default()
            });
        }
        let (pi, pj) = (self.frame.label_plane(vp.i)?, self.frame.label_plane(vp.j)?);
        let forward = vp
            .forward
            .map(|row| self.directed(row, vp.i, vp.j, &pi, &pj))
            .transpose()?;
        let backward = vp
            .backward
            .map(|row| self.directed(row, vp.j, vp.i, &pj, &pi))
            .transpose()?;
        self.ensure_view_extents(vp.i, Some(&pi))?;
        self.ensure_view_extents(vp.j, Some(&pj))?;
        let offsets = &self.frame.masks.mask_offsets;
        let links = graph::link_pair(
            forward.as_ref(),
            backward.as_ref(),
            [offsets[vp.i], offsets[vp.j]],
            &self.params,
        );
        let mut cells = CellCounts::default();
        for d in forward.iter().chain(backward.iter()) {
            cells.add(&d.cells);
        }
        Ok(PairResult {
            links,
            cells,
            skipped: false,
        })
    }

    pub(super) fn directed(
        &self,
        row: usize,
        src: usize,
        dst: usize,
        src_labels: &[u32],
        dst_labels: &[u32],
    ) -> Result<DirectedOverlaps> {
        let f = &self.frame;
        let warp = f.warp_plane(row);
        let certainty = f.certainty_plane(row);
        let vis = self.cell_visibility(src, dst)?;
        let grids = Grids {
            gw: f.gw,
            gh: f.gh,
            mw: f.mw,
            mh: f.mh,
            xmap: &f.xmap,
            ymap: &f.ymap,
        };
        let input = DirectedInput {
            src_view: src,
            dst_view: dst,
            src_labels,
            dst_labels,
            src_masks: f.masks.masks_in_view(src),
            dst_masks: f.masks.masks_in_view(dst),
            warp: &warp,
            certainty: &certainty,
            to_dst_mask: f.warp_to_mask(dst),
        };
        Ok(directed_pass(
            &grids,
            &input,
            self.params.tau_alpha,
            self.params.sampling,
            &vis,
        ))
    }

    pub(super) fn cell_visibility(&self, src: usize, dst: usize) -> Result<CellVisibility<'a>> {
        let f = &self.frame;
        let mut vis = CellVisibility::default();
        if f.cells() == 0 {
            return Ok(vis);
        }
        if self.visibility.uses_fwd_bwd() {
            if let Some(&rev) = f.pair_index.get(&(dst as u32, src as u32)) {
                let tol = f64::from(self.params.fwd_bwd_tolerance);
                vis.fwd_bwd = Some(FwdBwd {
                    reverse: f.warp_plane(rev),
                    to_dst_grid: f.warp_to_grid(dst),
                    to_src_grid: f.warp_to_grid(src),
                    gw: f.gw,
                    gh: f.gh,
                    tol2: tol * tol,
                });
            }
        }
        // The depth cache also serves the extents, so the mode decides.
        if let (true, Some(cache), Some(cameras)) =
            (self.visibility.uses_depth(), &self.depth, f.cameras)
        {
            let (z_row, z_offset) = relative_z(cameras, src, dst);
            vis.depth = Some(DepthTest {
                src: cache.get(src)?,
                dst: cache.get(dst)?,
                src_intrinsics: grid_camera(cameras, src, f.gw, f.gh)?.intrinsics,
                z_row,
                z_offset,
                to_dst_grid: f.warp_to_grid(dst),
                gw: f.gw,
                gh: f.gh,
                tol: f64::from(self.params.depth_tolerance),
            });
        }
        Ok(vis)
    }
}
