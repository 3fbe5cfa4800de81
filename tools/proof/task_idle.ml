(* Loaded into every WP run of make prove (compiled once by tools/proof/task_idle.py, loaded
   with frama-c -load-module; tools/proof/wp.py).

   Frama-C's command line waits for its provers in Task.on_idle, which polls the running
   solver calls and sleeps 50 ms between polls (src/libraries/utils/task.ml). With one solver
   call at a time (-wp-par 1) each call's verdict waited up to a poll, and the run stood idle
   for a fifth to a third of its time: the auth run 74 s of wall time for 50 s of CPU, link 14
   for 9 (issue 24's forty-seventh round). Polling every 2 ms instead, the same runs took 50
   and 7 s: the same goals, the same verdicts, and the solvers' limits untouched. *)
let () =
  Task.on_idle :=
    (fun f -> try while f () do Unix.sleepf 0.002 done with Db.Cancel -> ())
