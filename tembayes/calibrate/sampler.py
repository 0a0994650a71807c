"""emcee until converged, with a chunked checkpoint that survives ``kill -9``.

The moves are differential evolution (``emcee.moves.DEMove``) and, once an
earlier run has mapped the posterior, independence proposals from a
Student-t fitted to it (:class:`IndependenceMove`), half and half.  DE alone
mixes in ~75 steps on a correlated 21-dimensional Gaussian (the stretch
move: ~310), but on the calibration posteriors, whose rig nuisances are
skewed by their log-normal priors, in 200-350 steps; with the independence
half the laws' autocorrelation time drops to 80-100 steps and a module
needs ~13 000 steps instead of ~45 000 (bench module b3_00/TEM2, same
posterior).  Not emcee's ``DESnookerMove``: it does not leave the target
invariant (emcee 3.1.6 normalises the snooker axis by the square root of its
length, and halves the Jacobian's exponent).  Measured on that Gaussian,
started in it, 20 000 steps: sampled variances are 56 % of the true ones
with the snooker move alone, 75 % with the 80/20 DE/snooker mix used
before, 100 % with DE alone and with DE plus independence
proposals from a deliberately wrong fit
(``tests/test_calibrate_parts.py::test_sampler_returns_the_variance_of_a_known_gaussian``).

The first fifth of the chain is discarded as burn-in.  The run length is set
by convergence, checked every ``check_every`` stored iterations at *fixed*
iteration counts (so a resumed run stops exactly where an uninterrupted one
would):

- the chain after burn-in is at least ``min_tau_multiple`` (50) integrated
  autocorrelation times long, for every monitored parameter (the five module
  parameters; a weakly identified nuisance pair such as the bottom leak and
  its tab share can mix several times slower without biasing them -- their
  own autocorrelation times include that coupling);
- nested R-hat <= 1.01 (Margossian et al. 2024) and bulk ESS >= 1000 for
  every monitored parameter, computed with the walkers grouped into
  :data:`SUPERCHAINS` superchains.  Ensemble walkers are not independent
  chains, and the per-walker split R-hat asks every walker for ~100
  autocorrelation times however many walkers there are (its excess is
  about 2 tau / n): on the full model it doubled the run
  (45 000 steps instead of 18 000) for a bulk ESS five times the target.
  Nested R-hat compares groups of walkers: it still sees walkers that have
  not forgotten their start or that sit apart from the rest, and leaves the
  run length to the 50 tau and ESS targets.  The per-walker R-hat is
  reported (``rhat_walkers``).

A budget (``max_steps``) ends a run that does not converge, with a warning
and ``converged = False``.  The targets are those of every run; a caller may
loosen them for a quick look (:class:`Targets`).  The population stage
(:mod:`tembayes.calibrate.population`) runs on this driver too.

The chain is checkpointed at every convergence check (``check_every``
stored iterations, about a second of sampling): the new iterations, the
acceptance counts and the random state go to a new chunk file
``<checkpoint>.<k>.npz``, written to a temporary name and renamed into place.
A ``kill -9`` therefore leaves only whole chunks; ``resume=True`` rebuilds the
run from them and continues bit-identically, losing at most one check
interval.  (emcee's ``HDFBackend`` is not safe for this: it writes the random
state before the iteration counter, so a kill inside a write resumes with a
random state one stored iteration ahead of the chain.)  Seeding
(``docs/outputs.md``, 'Seeds'): the sampler's private ``RandomState`` is set from
the run's seed, never from the global one.
"""

from __future__ import annotations

import glob
import os
import warnings
import zipfile
from dataclasses import dataclass

import emcee
import numpy as np
from threadpoolctl import threadpool_limits

from tembayes.common.arvizlib import az

#: Convergence targets.
MIN_TAU_MULTIPLE = 50.0
RHAT_MAX = 1.01
ESS_MIN = 1000.0
#: Walker groups of the nested R-hat.
SUPERCHAINS = 4


@dataclass(frozen=True)
class Targets:
    """Convergence targets of :func:`sample`, monitored coordinates only.

    Attributes
    ----------
    tau_multiple : float
        Chain after burn-in at least this many integrated autocorrelation times long.
    rhat_max : float
        Nested R-hat at most this.
    ess_min : float
        Bulk ESS at least this.
    """

    tau_multiple: float = MIN_TAU_MULTIPLE
    rhat_max: float = RHAT_MAX
    ess_min: float = ESS_MIN


#: The targets of every run unless a caller loosens them for a quick look.
TARGETS = Targets()


class IndependenceMove(emcee.moves.MHMove):
    """Independence Metropolis-Hastings from a fixed multivariate Student-t.

    Proposals are ``mean + t_dof(0, scale^2 cov)``, whatever the walker's position.

    Exact for any proposal (the Hastings factor ``log q(x) - log q(x')``
    corrects it); fast when the proposal resembles the posterior, because
    then nearly independent draws are accepted at a high rate.  The heavy
    tails (``dof`` 5) keep the importance ratio bounded where the posterior's
    tails are heavier than a Gaussian fit to an earlier run.
    """

    def __init__(self, mean, cov, dof=5.0, scale=1.2):
        self.mean = np.asarray(mean, dtype=float)
        self.dof = float(dof)
        cov = np.asarray(cov, dtype=float)
        # a whisker of diagonal keeps a near-singular fit (a pinned coordinate) factorable
        self.chol = np.linalg.cholesky((cov + 1e-12 * np.diag(np.diag(cov))) * scale**2)
        self.chol_inv = np.linalg.inv(self.chol)
        super().__init__(self._propose, ndim=len(self.mean))

    def log_q(self, X):
        """Log proposal density (up to a constant) of ``(n, p)`` points."""
        Z = (np.atleast_2d(X) - self.mean) @ self.chol_inv.T
        return -0.5 * (self.dof + len(self.mean)) * np.log1p(np.sum(Z * Z, axis=1) / self.dof)

    def _propose(self, coords, random):
        n, p = coords.shape
        z = random.randn(n, p)
        g = random.chisquare(self.dof, n)
        X = self.mean + (z @ self.chol.T) * np.sqrt(self.dof / g)[:, None]
        return X, self.log_q(coords) - self.log_q(X)


@dataclass(frozen=True)
class SamplerRun:
    """Result of :func:`sample`.

    Attributes
    ----------
    chain : ndarray, shape (n, nw, p)
        Stored iterations after burn-in (coordinates).
    log_prob : ndarray, shape (n, nw)
    acceptance : ndarray, shape (nw,)
        Acceptance fraction of every walker.
    tau : ndarray, shape (p,)
        Integrated autocorrelation time of every coordinate [steps].
    rhat : ndarray, shape (p,)
        Nested R-hat over :data:`SUPERCHAINS` groups of walkers (the convergence target).
    rhat_walkers : ndarray, shape (p,)
        Rank-normalised split R-hat with every walker a chain (reported).
    ess_bulk, ess_tail : ndarray, shape (p,)
        arviz bulk and tail ESS over the stored chain (walkers as chains).
    steps : int
        Total sampler steps (including burn-in).
    burn : int
        Discarded stored iterations.
    thin_by : int
    converged : bool
    resumed : bool
    """

    chain: np.ndarray
    log_prob: np.ndarray
    acceptance: np.ndarray
    tau: np.ndarray
    rhat: np.ndarray
    rhat_walkers: np.ndarray
    ess_bulk: np.ndarray
    ess_tail: np.ndarray
    steps: int
    burn: int
    thin_by: int
    converged: bool
    resumed: bool


class ChunkCheckpoint:
    """Crash-safe checkpoint of an emcee run as a sequence of chunk files.

    Parameters
    ----------
    prefix : str or Path
        Files are ``<prefix>.<k>.npz``, ``k = 0, 1, ...``.
    """

    def __init__(self, prefix):
        self.prefix = os.fspath(prefix)

    def _path(self, k):
        return f"{self.prefix}.{k:05d}.npz"

    def chunks(self):
        """Paths of the stored chunks, in order (stops at the first gap)."""
        out = []
        while os.path.exists(self._path(len(out))):
            out.append(self._path(len(out)))
        return out

    def clear(self):
        """Remove every chunk (and stale temporary files) of this prefix."""
        for f in glob.glob(glob.escape(self.prefix) + ".*.npz*"):
            os.remove(f)

    def save(self, backend, start):
        """Write stored iterations ``start:`` of ``backend`` as the next chunk."""
        k = len(self.chunks())
        st = backend.random_state
        tmp = f"{self._path(k)}.tmp{os.getpid()}"
        with open(tmp, "wb") as f:
            np.savez(
                f,
                start=start,
                chain=backend.chain[start : backend.iteration],
                log_prob=backend.log_prob[start : backend.iteration],
                accepted=backend.accepted,
                rs_keys=st[1],
                rs_pos=st[2],
                rs_has_gauss=st[3],
                rs_gauss=st[4],
            )
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self._path(k))

    def _readable(self, files):
        """The chunks before the first damaged one.

        That one and the rest are set aside (renamed ``*.damaged``) with a
        warning, so the run continues from the last good chunk.
        """
        for k, path in enumerate(files):
            try:
                with np.load(path) as z:
                    for key in ("start", "chain", "log_prob", "accepted", "rs_keys"):
                        z[key]  # noqa: B018 -- reading every array finds a truncated file
            except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
                for bad in files[k:]:
                    os.replace(bad, bad + ".damaged")
                warnings.warn(
                    f"sampler checkpoint {path} cannot be read ({type(exc).__name__}: {exc}); it and the "
                    f"{len(files) - k - 1} later chunk(s) were renamed *.damaged and the module continues "
                    f"from {'chunk ' + str(k - 1) if k else 'the start'}",
                    RuntimeWarning,
                    stacklevel=3,
                )
                return files[:k]
        return files

    def load(self, nwalkers, ndim):
        """An in-memory :class:`emcee.backends.Backend` holding the stored run, or None if there is none.

        Raises
        ------
        ValueError
            If the chunks do not fit ``(nwalkers, ndim)`` or each other.
        """
        files = self._readable(self.chunks())
        if not files:
            return None
        chains, lps, n = [], [], 0
        for path in files:
            with np.load(path) as z:
                if int(z["start"]) != n or z["chain"].shape[1:] != (nwalkers, ndim):
                    raise ValueError(
                        f"checkpoint {path} does not continue the run "
                        f"(start {int(z['start'])}, shape {z['chain'].shape[1:]}; expected {n}, "
                        f"{(nwalkers, ndim)}); delete the run's checkpoints/ folder to start afresh"
                    )
                chains.append(z["chain"])
                lps.append(z["log_prob"])
                n += len(z["chain"])
                accepted = z["accepted"].copy()
                state = ("MT19937", z["rs_keys"].copy(), int(z["rs_pos"]), int(z["rs_has_gauss"]), float(z["rs_gauss"]))
        be = emcee.backends.Backend()
        be.reset(nwalkers, ndim)
        be.chain = np.concatenate(chains)
        be.log_prob = np.concatenate(lps)
        be.accepted = accepted
        be.iteration = n
        be.random_state = state
        return be


def random_state(seed):
    """A legacy ``RandomState`` state tuple for emcee from an integer seed."""
    return np.random.RandomState(int(seed) % (2**32)).get_state()


def nested_rhat(x, superchains=SUPERCHAINS):
    """Nested R-hat of one coordinate's ``(n, nw)`` chain, walkers in ``superchains`` groups.

    Each group's walkers are pooled, and each half of the chain is a separate
    superchain (split, as in split R-hat): ``sqrt(1 + B / W)`` with ``B`` the
    variance of the superchain means and ``W`` their mean within-superchain
    variance (Margossian et al. 2024, "Nested R-hat: assessing the
    convergence of Markov chain Monte Carlo when running many short chains",
    Bayesian Analysis).
    """
    n, nw = x.shape
    h = n // 2
    groups = np.array_split(np.arange(nw), superchains)
    pooled = [half[:, g].ravel() for half in (x[:h], x[h : 2 * h]) for g in groups]
    means = np.array([c.mean() for c in pooled])
    within = np.mean([c.var(ddof=1) for c in pooled])
    if within == 0:
        return float("nan")
    return float(np.sqrt(1.0 + means.var(ddof=1) / within))


def diagnostics(chain, monitor):
    """Nested R-hat, per-walker R-hat, bulk and tail ESS of coordinates of a ``(n, nw, p)`` chain.

    Only the ``monitor`` coordinates are computed; the others are NaN.
    """
    p = chain.shape[2]
    rhat, rhat_w, ess_b, ess_t = (np.full(p, np.nan) for _ in range(4))
    # arviz wants (chain, draw): walkers are the chains
    for j in monitor:
        x = np.ascontiguousarray(chain[:, :, j].T)
        rhat[j] = nested_rhat(chain[:, :, j])
        rhat_w[j] = float(az.rhat(x))
        ess_b[j] = float(az.ess(x, method="bulk"))
        ess_t[j] = float(az.ess(x, method="tail"))
    return rhat, rhat_w, ess_b, ess_t


def _burn(n):
    """Burn-in of a chain of ``n`` stored iterations: the first fifth."""
    return n // 5


def sample(
    log_prob,
    p0,
    *,
    seed,
    monitor,
    checkpoint=None,
    resume=False,
    thin_by=10,
    check_every=100,
    max_steps=60000,
    progress=False,
    label="",
    proposal=None,
    stop=None,
    targets=TARGETS,
    warning=RuntimeWarning,
    min_stored=0,
):
    """Run emcee until the convergence targets are met or the budget runs out.

    Parameters
    ----------
    log_prob : callable
        ``f(X (nw, p)) -> (nw,)`` log posterior density (vectorised).
    p0 : ndarray, shape (nw, p)
        Initial walkers.
    seed : int
        Seed of the sampler's random state.
    monitor : sequence of int
        Coordinates that must reach the R-hat and ESS targets.
    checkpoint : str or Path, optional
        Prefix of the checkpoint chunk files (see :class:`ChunkCheckpoint`);
        none if None.
    resume : bool
        Continue the run stored under ``checkpoint`` (its walkers and random
        state); start afresh if it holds none.
    thin_by : int
        Steps per stored iteration.
    check_every : int
        Stored iterations between convergence checks.
    max_steps : int
        Budget of sampler steps.
    progress : bool
        tqdm progress bar.
    label : str
        Name shown on the progress bar.
    proposal : (ndarray, ndarray), optional
        Mean ``(p,)`` and covariance ``(p, p)`` of an earlier run: half the
        moves are then :class:`IndependenceMove` proposals from it, half
        differential evolution.
    stop : callable, optional
        ``stop(chain, steps) -> bool``, asked at every convergence check with
        the chain after burn-in ``(n, nw, p)`` and the steps so far; True ends
        the run there (not converged).  Asked at the same step counts in a
        resumed run, so a resumed run stops where a straight one does.
    targets : Targets
        Convergence targets (default :data:`TARGETS`).
    warning : type
        Category of the warning issued when the run ends unconverged.
    min_stored : int
        A converged run has at least this many stored iterations after
        burn-in (the draws per walker its caller keeps: a batch's modules
        share one draw dimension).

    Returns
    -------
    SamplerRun
    """
    p0 = np.asarray(p0, dtype=float)
    nw, p = p0.shape
    # DE, not emcee's snooker move: that shrinks the sampled variance (module docstring)
    de = emcee.moves.DEMove()
    if proposal is not None:
        de = [(de, 0.5), (IndependenceMove(*proposal), 0.5)]
    resumed = False
    ckpt = None if checkpoint is None else ChunkCheckpoint(checkpoint)
    be = None
    if ckpt is not None:
        if resume:
            be = ckpt.load(nw, p)
            resumed = be is not None
        else:
            ckpt.clear()
    if be is None:
        be = emcee.backends.Backend()
    max_iter = max(check_every, max_steps // thin_by)
    kw = dict(thin_by=thin_by, progress=progress, progress_kwargs={"desc": label or "sampling", "leave": False})

    def run(sampler, n):
        start = p0 if sampler.iteration == 0 else None
        # one BLAS thread: the likelihood's products are small, and threads
        # fighting over 2 cores made them 30x slower
        with threadpool_limits(limits=1, user_api="blas"):
            sampler.run_mcmc(start, n, **kw)

    sampler = emcee.EnsembleSampler(nw, p, log_prob, vectorize=True, moves=de, backend=be)
    if sampler.iteration == 0:
        sampler.random_state = random_state(seed)
    converged = False
    while True:
        # check first: a resumed run may have stopped after its last check
        # (killed during the caller's post-processing) and must not grow
        if sampler.iteration > 0:
            chain = sampler.get_chain()
            b = _burn(len(chain))
            post = chain[b:]
            tau = thin_by * emcee.autocorr.integrated_time(post, c=5, tol=0, quiet=True)
            mon = list(monitor)
            # the run length serves the monitored (law) parameters; a weakly
            # identified nuisance ridge may mix slower without biasing them
            long_enough = thin_by * len(post) >= targets.tau_multiple * np.max(tau[mon]) and len(post) >= min_stored
            # arviz's diagnostics cost as much as ~1000 steps: only on a chain that may end here
            if long_enough:
                rhat, rhat_w, ess_b, ess_t = diagnostics(post, monitor)
                converged = bool(np.all(rhat[mon] <= targets.rhat_max) and np.all(ess_b[mon] >= targets.ess_min))
            if (
                converged
                or sampler.iteration >= max_iter
                or (stop is not None and stop(post, int(sampler.iteration * thin_by)))
            ):
                if not long_enough:
                    rhat, rhat_w, ess_b, ess_t = diagnostics(post, monitor)
                break
        done = sampler.iteration
        target = min(max_iter, (done // check_every + 1) * check_every)
        run(sampler, target - done)
        if ckpt is not None:
            ckpt.save(be, done)
    if not converged:
        warnings.warn(
            f"{label or 'sampler'}: not converged in {int(sampler.iteration * thin_by)} steps (budget {max_steps}) "
            f"(max tau {np.max(tau):.0f} steps, R-hat max {np.nanmax(rhat):.3f}, bulk ESS min {np.nanmin(ess_b):.0f}); "
            "results are marked converged: false",
            warning,
            stacklevel=2,
        )
    lp = sampler.get_log_prob()[b:]
    return SamplerRun(
        chain=post,
        log_prob=lp,
        acceptance=sampler.acceptance_fraction.copy(),
        tau=tau,
        rhat=rhat,
        rhat_walkers=rhat_w,
        ess_bulk=ess_b,
        ess_tail=ess_t,
        steps=int(sampler.iteration * thin_by),
        burn=b,
        thin_by=thin_by,
        converged=converged,
        resumed=resumed,
    )
