"""The pause before a child process is replaced: none after a long life, doubling after each
quick death in a row, capped."""

from imunoise.live.restart_pause import MAX_PAUSE_S, QUICK_DEATH_S, RestartPause, describe_exit


def test_quick_deaths_double_the_pause_up_to_the_cap_and_a_long_life_resets_it():
    now = [100.0]
    pause = RestartPause(clock=lambda: now[0])
    waits = []
    for _ in range(7):  # a child that dies 0.5 s after every start
        pause.started()
        now[0] += 0.5
        waits.append(pause.ended() - now[0])
        now[0] += waits[-1]
    assert waits == [1.0, 2.0, 4.0, 8.0, 16.0, MAX_PAUSE_S, MAX_PAUSE_S]
    pause.started()
    now[0] += QUICK_DEATH_S  # lived long enough: replaced at once, and the count starts over
    assert pause.ended() == now[0] and pause.quick_deaths == 0
    pause.started()
    now[0] += 1.0
    assert pause.ended() == now[0] + 1.0


def test_an_exit_code_in_words():
    assert describe_exit(-9) == "exit code -9 (signal 9)"
    assert describe_exit(1) == "exit code 1"
    assert describe_exit(0) == "exit code 0"
