# Shared by the job scripts (sourced): the benchmark argument, runs two at a time, python -m.

# is_benchmark WORD: WORD names a training scene (conf/scene/WORD.yaml, not a *_full preset)
is_benchmark() {
  [[ $1 != *=* && ! $1 =~ ^[0-9\ ]+$ && $1 != *_full && -f conf/scene/$1.yaml ]]
}

# check_benchmark SCRIPT WORD: stop (exit 2) with the known scenes unless WORD is one
check_benchmark() {
  is_benchmark "$2" && return 0
  echo "$1: no benchmark '$2': conf/scene/$2.yaml is not a training scene" \
    "(one of: $(ls conf/scene | sed -n 's/\.yaml$//p' | grep -v _full | paste -sd' ' -))" >&2
  exit 2
}

# two_lanes FUNCTION: FUNCTION ${jobs[i]} for every entry of the array jobs (words: its arguments),
# in two processes side by side (entries 0, 2, .. and 1, 3, ..); fails if either lane failed
two_lanes() {
  local fn=$1 status=0 first second
  lane() { local i; for ((i = $1; i < ${#jobs[@]}; i += 2)); do $fn ${jobs[$i]}; done; }
  lane 0 & first=$!
  lane 1 & second=$!
  wait $first || status=$?
  wait $second || status=$?
  return $status
}

# python_module MODULE [ARGS]: exec `python -m MODULE ARGS`, one thread per process unless the
# environment says otherwise, with .venv's python where set up (PYTHON overrides)
python_module() {
  export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} MKL_NUM_THREADS=${MKL_NUM_THREADS:-1} PYTHONWARNINGS=${PYTHONWARNINGS:-ignore}
  local python=${PYTHON:-.venv/bin/python}
  [ -x "$python" ] || python=python3
  exec "$python" -m "$@"
}
